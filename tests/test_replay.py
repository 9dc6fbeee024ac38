"""Lockstep replay, live replay against any reflex service, and compare."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.launch import load_script
from nwr.common.recordings import McapRecorder, Recorded, read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.core import Gateway, SimSkin, sim_settings
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.tools.recordings import analysis, compare
from nwr.services.tools.recordings.replay import select

DATA = Path(__file__).parent / "data"
DESC = load_description()


def skin_samples(script: str = "short.toml") -> list[m.SkinPressure]:
    """The skin stream of a touch script, from the gateway's cores (25 Hz, no network)."""
    profile = Profile()
    sim = SimSkin(sim_settings(profile.gateway), DESC.pads, load_script(str(DATA / script)))
    gateway = Gateway(profile.gateway, len(DESC.pads))
    out = []
    for i in range(int(load_script(str(DATA / script)).duration_s * 25)):
        t = (i + 1) / 25
        msg, _ = gateway.process(t, 10**9 + round(t * 1e9), sim.sample(t))
        out.append(msg)
    return out


def run_lockstep(strategy: str, samples: list[m.SkinPressure]) -> list[tuple[str, bytes, int]]:
    out: list[tuple[str, bytes, int]] = []
    Lockstep(Profile(), strategy=strategy).run(
        samples, lambda k, msg, t: out.append((k, msgspec.msgpack.encode(msg), t)))
    return out


def as_records(samples, produced) -> list[Recorded]:
    records = [Recorded("skin/pressure", s.stamp_ns, s) for s in samples]
    records += [Recorded(k, t, keys.codec(k).decode(b)) for k, b, t in produced]
    return sorted(records, key=lambda r: r.log_time_ns)


def test_lockstep_is_deterministic():
    samples = skin_samples()
    first, second = run_lockstep("location", samples), run_lockstep("location", samples)
    assert first == second
    assert any(keys.is_command(k) for k, _, _ in first)


@pytest.mark.parametrize("strategy", ["uniform", "cartesian"])
def test_lockstep_reproduces_the_pipeline_decisions(strategy):
    samples = skin_samples()
    touches = analysis.summarize(as_records(samples, run_lockstep(strategy, samples)), DESC)
    assert [t.name for t in touches] == ["upper_arm_top", "forearm_top", "wrist_2", "elbow_outer"]
    assert [t.reflex_seq > 0 for t in touches] == [False, True, True, False]
    for t in touches[1:3]:
        assert t.withdrawal_mm > 1.0
        if strategy == "cartesian":  # back at the saved pose after each reflex
            assert t.resumed_after_s is not None and t.return_error_rad < 1e-3
    # The uniform reflex moves far: within the Cartesian limits (0.5 m/s withdrawing, 0.25 m/s returning) its
    # returns take seconds, and this short script's next touch and end come first (test_limits has the full story).


@pytest.mark.parametrize("strategy", ["uniform", "cartesian"])
def test_a_standby_planner_s_statuses_do_not_change_the_summary(strategy):
    """A session with a standby planner (nwr up --planners, every study block) is summarised as one without.

    The standby planner mirrors the active one's mode a status period late and
    plans shadow reflexes: its statuses, mixed in, made every reflex look
    resumed 10 ms after its onset, with no withdrawal.
    """
    samples = skin_samples()
    records = as_records(samples, run_lockstep(strategy, samples))
    alone = analysis.summarize(records, DESC)
    standby: list[Recorded] = []
    mode = "TASK"
    for r in records:
        if r.key.startswith("reflex/") and r.key.endswith("/status"):
            st = r.message
            shadow = None if st.reflex is None else msgspec.structs.replace(st.reflex, shadow=True)
            standby.append(Recorded("reflex/standby/status", r.log_time_ns + 5_000_000, msgspec.structs.replace(
                st, name="standby", strategy="location", active=False, mode=mode, saved_pose=None, reflex=shadow,
                stamp_ns=st.stamp_ns + 5_000_000)))
            mode = st.mode  # one status late
    both = sorted(records + standby, key=lambda r: r.log_time_ns)
    assert analysis.summarize(both, DESC) == alone
    assert any(t.withdrawal_mm and t.withdrawal_mm > 1.0 for t in alone)


def test_select_by_topic_and_time():
    records = [Recorded("skin/pressure", 10**9 + i * 10**8, i) for i in range(50)]
    records.insert(3, Recorded("robot/state", 10**9 + 3 * 10**8, "x"))
    chosen = select(records, ["skin/pressure"], 1.0, 2.0)
    assert [r.message for r in chosen] == list(range(10, 21))


def write(path: Path, records: list[Recorded], strategy: str) -> Path:
    with path.open("wb") as stream:
        rec = McapRecorder(stream, "ur10e")
        rec.metadata("session", {"robot": "ur10e", "strategy": strategy})
        for r in records:
            rec.write(keys.key("ur10e", r.key), r.message, r.log_time_ns)
        rec.finish()
    return path


def test_compare_lines_up_touches_across_replays(tmp_path, capsys):
    samples = skin_samples()
    a = write(tmp_path / "a.mcap", as_records(samples, run_lockstep("uniform", samples)), "uniform")
    b = write(tmp_path / "b.mcap", as_records(samples, run_lockstep("cartesian", samples)), "cartesian")
    model = RobotModel(DESC)
    sessions = [compare.load_session(p, DESC, model) for p in (a, b)]
    rows = compare.line_up(sessions, 0.3)
    assert len(rows) == 4 and all(None not in row for row in rows)
    assert compare.peak_joint_speed(sessions[0], rows[1][0]) > compare.peak_joint_speed(sessions[1], rows[1][1])
    text = compare.table(sessions, rows)
    assert "a (uniform)" in text and "b (cartesian)" in text
    png = compare.figure(sessions, rows, model, tmp_path / "cmp.png")
    assert png.stat().st_size > 30_000


@pytest.mark.e2e
@pytest.mark.slow
def test_replay_fast_cli_and_live_against_the_outside_planner(tmp_path):
    samples = skin_samples()
    source = write(tmp_path / "session.mcap", [Recorded("skin/pressure", s.stamp_ns, s) for s in samples], "cartesian")
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = 17950\n[recorder]\ndirectory = "{tmp_path}"\n')
    cli = [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "--log-level", "WARNING"]

    fast = [subprocess.run([*cli, "replay", str(source), "--fast", "--reflex", "location",
                            "-o", str(tmp_path / f"f{i}.mcap")], capture_output=True, text=True, timeout=120)
            for i in range(2)]
    assert all(p.returncode == 0 for p in fast), fast[0].stderr
    decoded = [[(r.key, msgspec.msgpack.encode(r.message)) for r in read_recording(tmp_path / f"f{i}.mcap")[0]]
               for i in range(2)]
    assert decoded[0] == decoded[1]  # two --fast replays: identical messages

    example = Path(__file__).parents[1] / "examples" / "minimal_planner.py"
    planner = f"{sys.executable} {example} --name mini --base-port 17950"
    live = subprocess.run([*cli, "replay", str(source), "--planner-cmd", planner, "--name", "mini", "--start", "3.0",
                           "--end", "8.5", "-o", str(tmp_path / "live.mcap")],
                          capture_output=True, text=True, timeout=120)
    assert live.returncode == 0, live.stdout + live.stderr
    records, _ = read_recording(tmp_path / "live.mcap")
    states = [r.message for r in records if r.key == "robot/state"]
    assert {s.owner for s in states} == {"mini"}
    commands = [r.message for r in records if keys.is_command(r.key)]
    assert commands and {c.owner for c in commands} == {"mini"}
    onsets = {s.reflex_seq for s in states if s.accepted is not None}
    assert len(onsets) >= 2  # the two supra-threshold touches of the replayed window moved the arm
    assert max(np.abs(s.dq).max() for s in states) > 0.1  # and the arm moved


def test_a_lockstep_recording_prints_no_latency_and_says_why(tmp_path, capsys):
    from nwr.services.tools.recordings.replay import simulate
    from nwr.services.tools.recordings.summary import print_summary

    path = simulate(Profile(), str(Path(__file__).parent / "data" / "short.toml"), "cartesian",
                    tmp_path / "lockstep.mcap")[0]
    _, metadata = read_recording(path)
    assert metadata["session"]["timing"] == "lockstep"
    assert print_summary(path, None, Profile()) == 0
    out = capsys.readouterr().out
    assert "no latency is measured" in out and "median" not in out


def test_a_channel_of_a_few_messages_has_no_rate():
    from nwr.services.recorder.salvage import ChannelInfo

    events = ChannelInfo(1, "nwr/ur10e/control/active", "nwr.SwitchRequest", "json", count=2, first_log_ns=0,
                         last_log_ns=1_270_000)
    assert events.rate_hz is None  # was 787 Hz
    stream = ChannelInfo(2, "nwr/ur10e/robot/state", "nwr.RobotState", "json", count=51, first_log_ns=0,
                         last_log_ns=1_000_000_000)
    assert stream.rate_hz == pytest.approx(50.0)


def test_several_recordings_replay_in_lockstep_only_each_to_its_own_file(tmp_path, caplog):
    from nwr.services import cli

    samples = skin_samples()
    a = write(tmp_path / "a.mcap", [Recorded("skin/pressure", s.stamp_ns, s) for s in samples], "uniform")
    b = write(tmp_path / "sub_b.mcap", [Recorded("skin/pressure", s.stamp_ns, s) for s in samples], "uniform")
    (tmp_path / "sub").mkdir()
    same = write(tmp_path / "sub" / "a.mcap", [Recorded("skin/pressure", s.stamp_ns, s) for s in samples], "uniform")
    assert cli.main(["replay", str(a), str(b), "--reflex", "uniform"]) == 2
    assert "add --fast" in caplog.text
    assert cli.main(["replay", str(a), str(b), "--fast", "-o", str(tmp_path / "x.mcap")]) == 2
    assert "-o names one replay's recording" in caplog.text
    assert cli.main(["replay", str(a), str(same), "--fast"]) == 2
    assert "named alike" in caplog.text
    assert cli.main(["replay", str(a), str(b), "--fast", "--cluster", "tcp://127.0.0.1:9", "--jobs", "2"]) == 2
    assert "a --cluster's scheduler decides" in caplog.text


@pytest.mark.e2e
@pytest.mark.slow
def test_several_recordings_replayed_at_once_equal_their_replays_one_by_one(tmp_path):
    samples = skin_samples()
    sources = [write(tmp_path / f"s{i}.mcap", [Recorded("skin/pressure", s.stamp_ns, s) for s in samples],
                     "cartesian") for i in range(3)]
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[recorder]\ndirectory = "{tmp_path / "out"}"\n')
    cli = [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "--log-level", "WARNING"]
    many = subprocess.run([*cli, "replay", *map(str, sources), "--fast", "--reflex", "location", "--jobs", "2"],
                          capture_output=True, text=True, timeout=300)
    assert many.returncode == 0, many.stdout + many.stderr
    assert "3 of 3 recordings" in many.stdout and "2 at once" in many.stdout
    one = subprocess.run([*cli, "replay", str(sources[1]), "--fast", "--reflex", "location",
                          "-o", str(tmp_path / "one.mcap")], capture_output=True, text=True, timeout=120)
    assert one.returncode == 0, one.stderr

    def messages(path: Path) -> list[tuple[str, int, bytes]]:
        return [(r.key, r.log_time_ns, msgspec.msgpack.encode(r.message)) for r in read_recording(path)[0]]

    alone = messages(tmp_path / "one.mcap")
    assert any(keys.is_command(k) for k, _, _ in alone)
    for i in range(3):  # each replay the same as the one run alone (the same skin, the same strategy)
        assert messages(tmp_path / "out" / f"s{i}-replay-location.mcap") == alone

    # The same replays on a Dask cluster (a local one, on loopback) whose workers run in another working directory:
    # the files and the profile given relative to this command's, each replay the same again.
    distributed = pytest.importorskip("distributed")
    for i in range(3):
        (tmp_path / "out" / f"s{i}-replay-location.mcap").unlink()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1", dashboard_address=None,
                                  processes=True) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        on = subprocess.run([sys.executable, "-m", "nwr.services.cli", "--profile", "profile.toml", "--log-level",
                             "WARNING", "replay", *(s.name for s in sources), "--fast", "--reflex", "location",
                             "--cluster", cluster.scheduler_address],
                            capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert on.returncode == 0, on.stdout + on.stderr
    assert "3 of 3 recordings" in on.stdout and "on the Dask cluster at tcp://127.0.0.1:" in on.stdout
    for i in range(3):
        assert messages(tmp_path / "out" / f"s{i}-replay-location.mcap") == alone
    # No scheduler there: one clear line, nothing replayed.
    none = subprocess.run([*cli, "replay", str(sources[0]), "--fast", "--cluster", "tcp://127.0.0.1:9",
                           "--cluster-timeout", "1"], capture_output=True, text=True, timeout=120)
    assert none.returncode == 2 and "no Dask scheduler answered" in none.stderr, none.stdout + none.stderr
