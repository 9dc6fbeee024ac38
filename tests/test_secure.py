"""The secure LAN deployment on loopback: a TLS router with access control, the real services, and intruders.

A lab CA and one certificate per service (``nwr certs``), ``nwr router`` in
secure mode with ``deploy/acl.json5``, and every service started as its own
process with its own certificate (NWR_TLS_*), all on 127.0.0.1 (each router
on a free port: :class:`RoutedPipeline`). Intruders try to connect without a
certificate, with another CA's, and, with a recorder's, a view's and an
unlisted planner's certificate, to put on every key that moves or feeds the
arm; a standby planner's certificate sends commands the bridge must reject.
The session must run as if none of it happened. A standby planner's
certificate cannot pose as the active planner, and a planner's certificate
cannot command another arm through a router scoped to its own. A last test
compares the reflex onset latency through the router with and without TLS.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh
from pipeline import Pipeline, free_base_port

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import GainSection, ZenohSection
from nwr.common.errors import DecodeError
from nwr.common.launch import load_script
from nwr.common.node import zenoh_config
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services.gain.core import GainEstimator
from nwr.services.tools import certs, router
from nwr.services.tools.recordings import analysis

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
ACL = ROOT / "deploy" / "acl.json5"
SCRIPT = ROOT / "tests" / "data" / "short.toml"
ROBOT = "ur10e"
ACTIVE = "cartesian"
# Every intruder message carries this seq, so it can be told apart anywhere.
SENTINEL = 987_654_321
# The standby planner's commands posing as the active planner: SPOOF + n.
SPOOF = 123_000_000
# (certificate name, role): the pipeline's, plus those intruders hold.
ISSUED = [("router", "router"), ("gateway", "gateway"), ("gain", "gain"), ("cartesian", "planner"),
          ("uniform", "planner"), ("bridge", "bridge"), ("recorder", "recorder"), ("view", "view"),
          ("operator", "operator"), ("rogue", "planner")]  # rogue: signed by the CA, not in the rules


@dataclass
class Lab:
    directory: Path
    other: Path  # another CA's directory

    def tls(self, name: str, directory: Path | None = None) -> dict[str, str]:
        d = directory or self.directory
        return {"NWR_TLS_CA": str(self.directory / "ca.crt"), "NWR_TLS_CERT": str(d / f"{name}.crt"),
                "NWR_TLS_KEY": str(d / f"{name}.key")}

    def zenoh(self, port: int, name: str, directory: Path | None = None) -> ZenohSection:
        env = self.tls(name, directory)
        return ZenohSection(router=[f"tls/127.0.0.1:{port}"], secure=True, ca_certificate=env["NWR_TLS_CA"],
                            certificate=env["NWR_TLS_CERT"], private_key=env["NWR_TLS_KEY"])


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    base = tmp_path_factory.mktemp("certs")
    certs.init_ca(base / "lab")
    for name, role in ISSUED:
        certs.issue(base / "lab", name, role)
    for robot in ("arm-a", "arm-b"):  # one router for two arms (--robots): each arm's planner its own certificate
        certs.issue(base / "lab", ACTIVE, "planner", robot=robot)
    certs.init_ca(base / "other", lab="another lab")
    certs.issue(base / "other", ACTIVE, "planner")  # the right name, the wrong CA
    return Lab(base / "lab", base / "other")


def _wait_port(port: int, proc: subprocess.Popen[bytes], log: Path, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"router exited {proc.returncode}:\n{log.read_text()}"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"router did not listen on {port} within {timeout_s} s:\n{log.read_text()}")


class RoutedPipeline(Pipeline):
    """A router and the services, each its own process with its own certificate (or none, with ``lab=None``).

    The router listens on the pipeline's port (a free one); NWR_ROUTER makes every other process its client (the
    profile's mesh goes unused).
    """

    def __init__(self, tmp: Path, lab: Lab | None) -> None:
        super().__init__(tmp, port=free_base_port(width=1))
        self.lab = lab
        self.output = tmp / "session.mcap"

    def _env(self, cert: str | None) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("NWR_")}
        env["NWR_ROUTER"] = f"tcp/127.0.0.1:{self.port}"  # secure mode dials it as tls/
        if self.lab is not None and cert is not None:
            env.update(self.lab.tls(cert))
        return env

    def spawn(self, label: str, args: list[str], cert: str | None, *, ends: bool = False) -> subprocess.Popen[bytes]:
        return self.start(label, *args, env=self._env(cert), ends=ends)

    def start_router(self) -> None:
        args = ["router", "--listen", f"tcp/127.0.0.1:{self.port}"]
        if self.lab is not None:
            args += ["--acl", str(ACL)]
        proc = self.spawn("router", args, "router")
        _wait_port(self.port, proc, self.tmp / "router.log")

    def start_services(self, script: Path) -> None:
        self.spawn("bridge", ["run", "bridge", "--active", ACTIVE], "bridge")
        self.spawn("planner", ["run", "planner", "--name", ACTIVE, "--reflex", ACTIVE], ACTIVE)
        self.spawn("gain", ["run", "gain"], "gain")
        self.spawn("recorder", ["run", "recorder", "--session", "secure", "--output", str(self.output),
                                "--strategy", ACTIVE], "recorder")
        self.spawn("gateway", ["run", "gateway", "--wait-for", f"bridge,gain,recorder,planner-{ACTIVE}",
                               "--script", str(script), "--exit-at-end"], "gateway", ends=True)

    def wait_gateway(self, timeout_s: float) -> None:
        """Until the gateway has ended the session (every other process still running), then the last return."""
        gateway = self.procs["gateway"]
        self.wait_until(lambda: gateway.poll() is not None, timeout_s, "the session's end", every_s=0.2)
        assert gateway.returncode == 0, self.log("gateway")
        time.sleep(2.0)  # the last return, and the recorder catching up

    def stop_all(self, *, sig: signal.Signals = signal.SIGTERM, grace_s: float = 15.0) -> dict[str, int]:
        """SIGTERM to every process, the last started first; every exit code."""
        return super().stop_all(sig=sig, grace_s=grace_s)


@pytest.fixture()
def pipeline_factory(tmp_path: Path) -> Iterator[list[RoutedPipeline]]:
    started: list[RoutedPipeline] = []
    yield started
    for p in started:
        p.stop_all()


# -- intruders ------------------------------------------------------------
def _open_fails(conf: zenoh.Config) -> str:
    """The error a session that must not connect gets (the test fails if it connects)."""
    conf.insert_json5("connect/timeout_ms", "3000")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        return str(exc)
    session.close()
    raise AssertionError("the intruder's session connected")


def no_certificate(lab: Lab, port: int) -> str:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    # It trusts the router (has the CA's certificate) but has no key of its own.
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(lab.directory / "ca.crt")))
    return _open_fails(conf)


def plain_tcp(port: int) -> str:
    conf = zenoh_config(ZenohSection(router=[f"tcp/127.0.0.1:{port}"]))
    return _open_fails(conf)


def other_ca(lab: Lab, port: int) -> str:
    return _open_fails(zenoh_config(lab.zenoh(port, ACTIVE, lab.other)))


@dataclass
class Intrusion:
    """What the intruders holding the lab's own certificates did and saw."""

    received: dict[str, int] = field(default_factory=dict)  # certificate -> samples it could subscribe to
    sent: dict[str, int] = field(default_factory=dict)  # certificate -> sentinel puts
    standby_sent: int = 0


def _templates(session: zenoh.Session, wanted: set[str], timeout_s: float) -> dict[str, object]:
    """One real message of each wanted key, to replay with the sentinel seq."""
    found: dict[str, object] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        relative = keys.relative_key(ROBOT, str(sample.key_expr))
        if relative in wanted and relative not in found:
            try:
                message = keys.codec(relative).decode(sample.payload.to_bytes())
            except DecodeError:
                return
            with lock:
                found[relative] = message

    sub = session.declare_subscriber(keys.key(ROBOT, "**"), on_sample)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and len(found) < len(wanted):
        time.sleep(0.05)
    sub.undeclare()
    return found


def insider(lab: Lab, port: int, cert: str, stop: threading.Event, report: Intrusion) -> None:
    """A stolen recorder / view certificate (or an unlisted planner's): subscribe, then put on every key that counts."""
    wanted = {keys.SKIN_PRESSURE, keys.SKIN_PAIN, keys.ROBOT_STATE, keys.planner_status(ACTIVE)}
    with zenoh.open(zenoh_config(lab.zenoh(port, cert))) as session:
        count = [0]
        counter = session.declare_subscriber(keys.key(ROBOT, "**"), lambda _s: count.__setitem__(0, count[0] + 1))
        templates = _templates(session, wanted, timeout_s=8.0)
        report.received[cert] = count[0]
        counter.undeclare()
        forged = [(keys.key(ROBOT, relative), keys.codec(relative).encode(
            msgspec.structs.replace(message, seq=SENTINEL)))  # type: ignore[type-var]
            for relative, message in templates.items()]
        # Posing as the active planner, driving wrist 3 at 3 rad/s.
        forged.append((keys.key(ROBOT, keys.robot_command(ACTIVE)), keys.codec(keys.robot_command(ACTIVE)).encode(
            m.VelocityCommand(seq=SENTINEL, stamp_ns=time.monotonic_ns(), owner=ACTIVE, dq=[0.0] * 5 + [3.0],
                              trace=m.Trace(0, 0), phase="REFLEX"))))
        forged.append((keys.key(ROBOT, keys.CONTROL_ACTIVE), keys.codec(keys.CONTROL_ACTIVE).encode(
            m.SwitchRequest(seq=SENTINEL, stamp_ns=0, name="uniform", requested_by=cert))))
        token = session.liveliness().declare_token(keys.key(ROBOT, keys.alive("bridge")))  # a fake bridge
        n = 0
        while not stop.wait(0.02):
            for key_expr, payload in forged:
                session.put(key_expr, payload)
                n += 1
        token.undeclare()
        report.sent[cert] = n


def standby_planner(lab: Lab, port: int, stop: threading.Event, report: Intrusion) -> None:
    """The standby planner's own certificate: commands under its own name, and posing as the active planner.

    Under its own name on its own key: they arrive, and the bridge refuses
    them (not the active planner). Claiming the active planner's name on its
    own key: the bridge refuses them (the key names the publisher). On the
    active planner's key: the router drops them.
    """
    with zenoh.open(zenoh_config(lab.zenoh(port, "uniform"))) as session:
        own = session.declare_publisher(keys.key(ROBOT, keys.robot_command("uniform")))
        active = session.declare_publisher(keys.key(ROBOT, keys.robot_command(ACTIVE)))
        codec = keys.codec(keys.robot_command("uniform"))
        time.sleep(3.0)
        seq = 0
        while not stop.wait(0.05):
            now = time.monotonic_ns()
            own.put(codec.encode(m.VelocityCommand(seq=seq, stamp_ns=now, owner="uniform",
                                                   dq=[0.0] * 5 + [3.0], trace=m.Trace(0, 0))))
            spoof = m.VelocityCommand(seq=SPOOF + seq, stamp_ns=now, owner=ACTIVE, dq=[0.0] * 5 + [3.0],
                                      trace=m.Trace(0, 0), phase="REFLEX")
            own.put(codec.encode(spoof))
            active.put(codec.encode(spoof))
            seq += 1
        report.standby_sent = seq


def observer(lab: Lab, port: int, stop: threading.Event, seen: dict[str, int]) -> None:
    """A legitimate subscriber (the operator's certificate): counts the sentinel messages that reach it, per key."""

    def on_sample(sample: zenoh.Sample) -> None:
        relative = keys.relative_key(ROBOT, str(sample.key_expr))
        seen["total"] = seen.get("total", 0) + 1
        try:
            message = keys.codec(relative).decode(sample.payload.to_bytes())
        except DecodeError:
            return
        if getattr(message, "seq", None) == SENTINEL:
            seen[relative] = seen.get(relative, 0) + 1

    with zenoh.open(zenoh_config(lab.zenoh(port, "operator"))) as session:
        session.declare_subscriber(keys.key(ROBOT, "**"), on_sample)
        stop.wait()


# -- the tests ------------------------------------------------------------
def _check_session(records: list, script_path: Path) -> list[float]:  # type: ignore[type-arg]
    """Every touch above threshold caused a reflex that returned and resumed; the onset latencies."""
    desc = load_description()
    touches = analysis.summarize(records, desc)
    script = load_script(str(script_path))
    estimator = GainEstimator(GainSection(), desc.pads)
    latencies = []
    for scripted in script.touch:
        t0 = min(r.message.stamp_ns for r in records if r.key == "skin/pressure")
        touch = next(t for t in touches if t.name == scripted.pad
                     and abs((t.start_ns - t0) / 1e9 - scripted.start_s) < 0.6)
        _, gain = estimator.gain(touch.pad, scripted.peak_hpa)
        if gain > 0:
            assert touch.reflex_seq > 0, touch
            assert touch.onset_latency_ms is not None and touch.onset_latency_ms > 0, touch
            assert touch.resumed_after_s is not None, touch
            latencies.append(touch.onset_latency_ms)
        else:
            assert touch.reflex_seq == 0, touch
    status = [r.message for r in records if r.key == f"reflex/{ACTIVE}/status"]
    last_reflex = max(i for i, s in enumerate(status) if s.mode == "REFLEX")
    after = [s for s in status[last_reflex:] if s.mode == "TASK"]
    assert after and after[-1].task_time_s > after[0].task_time_s + 1.0, "the task did not resume"
    return latencies


def test_refuses_to_start_without_a_certificate(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NWR_")}
    env.update({"NWR_ROUTER": "tcp/127.0.0.1:18199", "NWR_TLS_CA": str(tmp_path / "ca.crt"),
                "NWR_TLS_CERT": str(tmp_path / "nothing.crt"), "NWR_TLS_KEY": str(tmp_path / "nothing.key")})
    proc = subprocess.run([sys.executable, "-m", "nwr.services.cli", "run", "gain"], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "secure mode" in proc.stderr and "nwr certs issue" in proc.stderr, proc.stderr


def test_intruders_against_the_secure_pipeline(lab: Lab, tmp_path: Path, pipeline_factory: list[RoutedPipeline],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    pipeline = RoutedPipeline(tmp_path, lab)
    port = pipeline.port
    pipeline_factory.append(pipeline)
    pipeline.start_router()

    # At the door: no certificate, plain TCP, a certificate of another CA.
    refused = {"no certificate": no_certificate(lab, port), "plain tcp": plain_tcp(port),
               "another CA": other_ca(lab, port)}

    stop_intruders, stop_observer = threading.Event(), threading.Event()
    report, seen = Intrusion(), {}
    threads = [threading.Thread(target=observer, args=(lab, port, stop_observer, seen), daemon=True)]
    threads += [threading.Thread(target=insider, args=(lab, port, cert, stop_intruders, report), daemon=True)
                for cert in ("recorder", "view", "rogue")]
    threads.append(threading.Thread(target=standby_planner, args=(lab, port, stop_intruders, report), daemon=True))
    for t in threads:
        t.start()
    pipeline.start_services(SCRIPT)
    try:
        pipeline.wait_gateway(timeout_s=90)
    finally:
        stop_intruders.set()
        for t in threads[1:]:
            t.join(10)
    time.sleep(0.5)
    stop_observer.set()
    threads[0].join(10)
    codes = pipeline.stop_all()
    assert all(c in (0, -signal.SIGTERM) for c in codes.values()), codes
    for name in ("gateway", "gain", "planner", "bridge", "recorder"):
        assert "secure mode: mutual TLS" in pipeline.log(name), pipeline.log(name)
    assert "access control from" in pipeline.log("router")

    # The lab's own certificates could subscribe (the rogue one is in no rule:
    # it reads nothing) and sent plenty.
    assert report.received["recorder"] > 10 and report.received["view"] > 10, report
    assert report.received.get("rogue", 0) == 0, report
    assert set(report.sent) == {"recorder", "view", "rogue"} and min(report.sent.values()) > 100, report
    assert report.standby_sent > 20, report

    # Not one forged message reached a legitimate subscriber...
    assert seen.get("total", 0) > 1000, seen
    assert {k: v for k, v in seen.items() if k != "total"} == {}, seen
    # ... nor the recording.
    records, _ = read_recording(pipeline.output)
    forged = [r for r in records if getattr(r.message, "seq", None) == SENTINEL]
    assert forged == [], forged[:3]
    states = [r.message for r in records if r.key == "robot/state"]
    assert {s.owner for s in states} == {ACTIVE}  # no switch went through
    assert max(abs(s.dq[5]) for s in states) < 0.5  # nobody's 3 rad/s on wrist 3 reached the arm
    # The standby planner's commands arrived (its certificate may command) and were refused.
    standby = [r for r in records if r.key == keys.robot_command("uniform") and r.message.owner == "uniform"]
    assert standby
    rejected = [r.message for r in records if r.key == "diag/bridge" and r.message.code == "command_rejected"]
    assert rejected and any("uniform" in d.message for d in rejected), rejected[:3]
    # Posing as the active planner: on its own key, recorded and refused by the bridge (the key names
    # the publisher); on the active planner's key, dropped by the router.
    spoofs = [r for r in records if keys.is_command(r.key) and r.message.seq >= SPOOF]
    assert spoofs and {r.key for r in spoofs} == {keys.robot_command("uniform")}, {r.key for r in spoofs}
    spoofed = [r.message for r in records if r.key == "diag/bridge" and r.message.code == "command_spoofed"]
    assert spoofed and all(f"claims owner '{ACTIVE}'" in d.message for d in spoofed), spoofed[:3]
    assert max(s.rejected for s in states) > 20

    # The session ran as if none of it happened.
    latencies = _check_session(records, SCRIPT)
    assert latencies
    with capsys.disabled():
        print("\nattacks refused at the door:")
        for what, error in refused.items():
            print(f"  {what:<15s} {error.splitlines()[0][:110]}")
        print(f"insiders' forged puts: {report.sent} (subscribed samples {report.received}); "
              f"standby planner commands: {report.standby_sent}, bridge rejections: {max(s.rejected for s in states)}; "
              f"sentinel messages at the observer: 0 of {seen['total']}, in the recording: 0 of {len(records)}")
        print(f"reflex onset under attack: {', '.join(f'{x:.2f}' for x in latencies)} ms")


def test_fake_liveliness_token_is_not_seen(lab: Lab, tmp_path: Path, pipeline_factory: list[RoutedPipeline]
                                           ) -> None:
    """A recorder certificate cannot announce itself as the bridge (or the active planner)."""
    pipeline = RoutedPipeline(tmp_path, lab)
    port = pipeline.port
    pipeline_factory.append(pipeline)
    pipeline.start_router()
    with zenoh.open(zenoh_config(lab.zenoh(port, "recorder"))) as spy, \
            zenoh.open(zenoh_config(lab.zenoh(port, "operator"))) as operator:
        fake = spy.liveliness().declare_token(keys.key(ROBOT, keys.alive(f"planner-{ACTIVE}")))
        own = spy.liveliness().declare_token(keys.key(ROBOT, keys.alive("recorder")))
        time.sleep(1.0)
        alive = sorted(str(r.ok.key_expr).rsplit("/", 1)[-1]
                       for r in operator.liveliness().get(keys.key(ROBOT, "alive/*"), timeout=2.0) if r.ok)
        fake.undeclare()
        own.undeclare()
    assert alive == ["recorder", "router"], alive


def _latency_script(path: Path, touches: int) -> Path:
    """Supra-threshold touches every 2 s on pads that alternate (PL 3 and PL 4)."""
    pads = ["forearm_top", "wrist_2", "upper_arm_top"]
    # 3 s more than the last touch's reflex needs: a return waits while the task would go through where a touch
    # just was (planner.recent_contact_s), and the task must resume before the session ends.
    lines = [f"duration_s = {2.0 * touches + 6.0}"]
    for i in range(touches):
        lines += ["[[touch]]", f'pad = "{pads[i % len(pads)]}"', f"start_s = {2.0 + 2.0 * i}", "duration_s = 0.3",
                  f"peak_hpa = {9.0 if i % 2 else 18.0}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_tls_latency_cost(lab: Lab, tmp_path: Path, pipeline_factory: list[RoutedPipeline],
                          capsys: pytest.CaptureFixture[str]) -> None:
    """Reflex onset latency through the router, plain TCP against mutual TLS with access control."""
    script = _latency_script(tmp_path / "latency.toml", touches=15)
    results = {}
    for mode in ("tcp", "tls"):
        tmp = tmp_path / mode
        tmp.mkdir()
        pipeline = RoutedPipeline(tmp, lab if mode == "tls" else None)
        pipeline_factory.append(pipeline)
        pipeline.start_router()
        pipeline.start_services(script)
        pipeline.wait_gateway(timeout_s=120)
        pipeline.stop_all()
        records, _ = read_recording(pipeline.output)
        results[mode] = _check_session(records, script)
        assert len(results[mode]) == 15
    with capsys.disabled():
        print("\nreflex onset latency through the router (skin sample stamped -> first command accepted):")
        for mode, lat in results.items():
            print(f"  {mode}: median {np.median(lat):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, "
                  f"max {max(lat):.2f} ms over {len(lat)} reflexes")


@pytest.mark.parametrize("scope", ["own", "all", "per-robot"])
def test_router_scoped_to_its_robot(lab: Lab, scope: str) -> None:
    """A planner's certificate puts on two arms' robot/command; the router passes only what its rules allow.

    The router runs in this process, so its own session subscribes to
    everything behind the access control, which filters what a client
    sends (ingress). ``own``: a router of ``ur10e`` passes its arm's only.
    ``all`` (``--all-robots``, the control): both arrive. ``per-robot``
    (``--robots arm-a,arm-b``, one router for two arms): each arm's planner
    certificate (``planner:cartesian@arm-a``) reaches its own arm only, and
    a certificate of no robot (``planner:cartesian``) neither.
    """
    port = 18190 + ["own", "all", "per-robot"].index(scope)
    robots = ["arm-a", "arm-b"] if scope == "per-robot" else [ROBOT, "ur5e"]
    acl = router.load_acl(ACL, ROBOT if scope == "own" else None, robots if scope == "per-robot" else None)
    conf = router.router_config([f"tcp/127.0.0.1:{port}"], [], tls=lab.zenoh(port, "router"), acl=acl)
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    seen: dict[tuple[str, str], int] = {}
    lock = threading.Lock()
    senders = {"arm-a": lab.directory / "arm-a", "arm-b": lab.directory / "arm-b", "none": lab.directory} \
        if scope == "per-robot" else {"none": lab.directory}

    def on_sample(sample: zenoh.Sample) -> None:
        robot = str(sample.key_expr).split("/")[1]
        sender = sample.payload.to_bytes().decode()
        with lock:
            seen[sender, robot] = seen.get((sender, robot), 0) + 1

    with zenoh.open(conf) as server:
        server.declare_subscriber("nwr/**", on_sample)
        for sender, directory in senders.items():
            with zenoh.open(zenoh_config(lab.zenoh(port, ACTIVE, directory))) as planner:
                for robot in robots:
                    for _ in range(20):
                        planner.put(keys.key(robot, keys.robot_command(ACTIVE)), sender.encode())
                time.sleep(0.5)
        want = {"own": {("none", ROBOT): 20}, "all": {("none", ROBOT): 20, ("none", "ur5e"): 20},
                "per-robot": {("arm-a", "arm-a"): 20, ("arm-b", "arm-b"): 20}}[scope]
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and seen != want:
            time.sleep(0.05)
        time.sleep(0.5)  # anything late for the other arm would arrive now
    assert seen == want, seen
