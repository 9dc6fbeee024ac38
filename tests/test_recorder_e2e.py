"""kill -9 of the recorder in a live pipeline, then `nwr recover`: all but the last ~second is saved."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
import zenoh
from pipeline import SHORT_SCRIPT, Pipeline

from nwr.common import keys
from nwr.common.errors import DecodeError
from nwr.common.recordings import publisher_of, read_recording
from nwr.services.recorder import salvage

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOT = "ur10e"
RUN_BEFORE_KILL_S = 5.0
# What a kill -9 may cost: the chunk in memory (recorder.chunk_interval_s =
# 0.5 s by default) plus the recorder loop's polling and queue.
MAX_LOSS_S = 1.0


def _children(pid: int) -> dict[int, str]:
    """Child processes of ``pid`` and their command lines (Linux /proc)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                found[int(entry.name)] = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError, IndexError):
            continue  # the process ended while we looked
    return found


def test_recorder_killed_mid_session_is_recovered(tmp_path: Path, pipeline: Pipeline) -> None:
    output = tmp_path / "killed.mcap"

    # A reference subscriber: what the pipeline published, and when it arrived.
    seen: list[tuple[str, str, int, int]] = []

    def on_sample(sample: zenoh.Sample) -> None:
        relative = keys.relative_key(ROBOT, str(sample.key_expr))
        try:
            message = keys.codec(relative).decode(sample.payload.to_bytes())
        except DecodeError:
            return
        seen.append((relative, publisher_of(message), message.seq, time.monotonic_ns()))

    with pipeline.session() as session:
        sub = session.declare_subscriber(f"{keys.prefix(ROBOT)}/**", on_sample)
        up = pipeline.start("up", "up", "--script", str(SHORT_SCRIPT), "--output", str(output))
        try:
            pipeline.wait_until(lambda: any(key == keys.SKIN_PRESSURE for key, *_ in seen), 30.0,
                                "the first skin sample (every service is up)")
            time.sleep(RUN_BEFORE_KILL_S)
            recorders = [pid for pid, cmd in _children(up.pid).items() if " run recorder" in cmd]
            assert len(recorders) == 1, _children(up.pid)
            t_kill = time.monotonic_ns()
            os.kill(recorders[0], signal.SIGKILL)
            time.sleep(0.3)
        finally:
            pipeline.stop("up", sig=signal.SIGTERM, grace_s=30.0)  # the launcher stops the rest
            log = pipeline.log("up")
        sub.undeclare()

    assert output.exists(), log
    assert not salvage.info_file(output).footer  # the killed recorder left no summary or footer

    recovered = tmp_path / "recovered.mcap"
    proc = pipeline.run("recover", str(output), "-o", str(recovered), timeout_s=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    print(proc.stdout)
    assert "NOT finished" in proc.stdout and "lost:" in proc.stdout

    records, metadata = read_recording(recovered)  # a valid file, every message decodes
    assert metadata["session"]["robot"] == ROBOT and metadata["recovery"]["finished"] == "false"
    have = {(r.key, publisher_of(r.message), r.message.seq) for r in records}
    first_ns = min(r.log_time_ns for r in records)
    last_ns = max(r.log_time_ns for r in records)
    assert last_ns < t_kill
    lost_s = (t_kill - last_ns) / 1e9
    print(f"\nkill -9 after {(t_kill - first_ns) / 1e9:.1f} s of recording: {len(records)} messages saved, "
          f"the last one {lost_s * 1e3:.0f} ms before the kill")
    assert lost_s <= MAX_LOSS_S

    # Everything the reference saw from shortly after the recorder's first
    # message to MAX_LOSS_S before the kill is in the recovered file.
    window = [(key, pub, seq) for key, pub, seq, t in seen
              if first_ns + 200_000_000 <= t <= t_kill - MAX_LOSS_S * 1e9 and not key.startswith("diag/")]
    missing = [w for w in window if w not in have]
    assert len(window) > 500  # about 200 messages a second while the arm does its task
    assert not missing, missing[:10]
    lost = [(key, pub, seq) for key, pub, seq, t in seen if last_ns < t < t_kill]
    print(f"messages the reference saw after the last saved one and before the kill: {len(lost)}")
    gaps = {k: v for k, v in json.loads(metadata["recording"]["gaps"]).items() if v}
    assert not gaps
