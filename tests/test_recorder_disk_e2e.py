"""`nwr up` recording onto a real small file system: it fills, or is read-only; the arm and the services go on.

The recording goes to a tmpfs mounted for the test (``mount -t tmpfs``,
unmounted at the end): it needs root, and the test is skipped, with the
reason, where mounting is not permitted. A read-only file system is mounted
read-only from the start: Linux refuses ``mount -o remount,ro`` while a file
on it is open for writing (EBUSY), so a recorder never sees one turn
read-only under an open file except by a disk error (``errors=remount-ro``);
tests/test_recorder_disk.py injects that case.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from typing import Any

import pytest
import zenoh
from pipeline import Pipeline, free_base_port
from test_recorder_disk import remount

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError
from nwr.services.recorder.disk import NOT_WRITING, RECORDING_RESUMED, WRITE_FAILED

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOT = "ur10e"
# Free space left to the recording on the "full" disk: at about 50 kB/s it is full within seconds.
ROOM = 200 * 1024
# Guards, not measurements: how long to wait for something that must happen before calling the test failed.
WAIT_S = 90.0
# How long the pipeline is watched once the recorder stopped writing.
WATCH_S = 4.0


class Watch:
    """What the pipeline publishes: robot states, planner statuses and the recorder's diagnostics, with arrival."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[float, m.RobotState]] = []
        self.statuses: list[tuple[float, m.PlannerStatus]] = []
        self.diags: list[tuple[float, m.Diagnostic]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        relative = keys.relative_key(ROBOT, str(sample.key_expr))
        if relative not in (keys.ROBOT_STATE, keys.diag("recorder")) and not relative.endswith("/status"):
            return
        try:
            message = keys.codec(relative).decode(sample.payload.to_bytes())
        except DecodeError:
            return
        now = time.monotonic()
        with self.lock:
            match message:
                case m.RobotState():
                    self.states.append((now, message))
                case m.PlannerStatus():
                    self.statuses.append((now, message))
                case m.Diagnostic():
                    self.diags.append((now, message))

    def diag(self, code: str, after: float = 0.0) -> tuple[float, m.Diagnostic] | None:
        with self.lock:
            return next(((t, d) for t, d in self.diags if d.code == code and t >= after), None)

    def wait_diag(self, code: str, pipeline: Pipeline, after: float = 0.0) -> tuple[float, m.Diagnostic]:
        return pipeline.wait_until(lambda: self.diag(code, after), WAIT_S, f"{code} on diag/recorder")

    def wait_moving(self, pipeline: Pipeline) -> None:
        """Until the bridge follows the planner's commands (``ok``; ``idle`` before the first one)."""
        pipeline.wait_until(lambda: any(s.status == "ok" for s in self.since(time.monotonic() - 1.0)[0]),
                            WAIT_S, "robot/state ok")

    def since(self, t0: float) -> tuple[list[m.RobotState], list[m.PlannerStatus]]:
        with self.lock:
            return [s for t, s in self.states if t >= t0], [s for t, s in self.statuses if t >= t0]


def assert_arm_keeps_its_task(states: list[m.RobotState], statuses: list[m.PlannerStatus]) -> None:
    """The bridge kept publishing a moving arm under the planner's command, and the planner kept its task going."""
    assert len(states) > 50, len(states)  # the bridge publishes at 50 Hz
    # The recorder's disk takes nothing from the arm: it is under command throughout, but for a late command
    # (stale_command) that a loaded machine may cause now and then, whatever the recorder does.
    statuses_seen = [s.status for s in states]
    assert set(statuses_seen) <= {"ok", "stale_command"}, set(statuses_seen)
    assert statuses_seen.count("ok") >= 0.9 * len(statuses_seen), statuses_seen
    assert {s.owner for s in states} == {"cartesian"}
    moved = max(abs(a - b) for a, b in zip(states[0].q, states[-1].q))
    assert moved > 1e-3, moved  # the figure-eight goes on
    assert statuses and all(s.active for s in statuses)
    assert statuses[-1].task_time_s > statuses[0].task_time_s  # its task's clock runs


def nwr_status(pipeline: Pipeline) -> str:
    proc = subprocess.run([sys.executable, "-m", "nwr.services.tools.status", "--profile", str(pipeline.profile),
                           "--window", "2.5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def test_a_full_disk_stops_neither_the_arm_nor_the_services_and_recording_resumes(tmpfs: Any, pipeline: Pipeline
                                                                                  ) -> None:
    disk = tmpfs("size=4m")
    st = os.statvfs(disk)
    filler = disk / "filler"
    filler.write_bytes(b"\0" * (st.f_bavail * st.f_frsize - ROOM))  # what a lab PC's other files leave
    output = disk / "s.mcap"
    watch = Watch()
    with pipeline.session() as session:
        sub = session.declare_subscriber(f"{keys.prefix(ROBOT)}/**", watch)
        pipeline.start("up", "up", "--output", str(output))
        try:
            t_fail, failed = watch.wait_diag(WRITE_FAILED, pipeline)
            assert "disk full (No space left on device, ENOSPC)" in failed.message
            assert "finished it in the space held in reserve" in failed.message
            time.sleep(WATCH_S)
            assert_arm_keeps_its_task(*watch.since(t_fail))
            with watch.lock:
                reports = [d for t, d in watch.diags if t > t_fail]
            not_writing = [d for d in reports if d.code == NOT_WRITING]
            assert 2 <= len(not_writing) <= len(reports) <= 2 * WATCH_S + 2  # once a retry, not once a message
            assert "disk full" in not_writing[-1].message and "free space on the disk" in not_writing[-1].message
            text = nwr_status(pipeline)
            print(text)
            assert "recorder: not writing" in text and "disk full" in text
            assert "not alive" not in text  # every service is there, the recorder too

            info = pipeline.run("info", str(output))  # finished, valid: exit 0
            assert info.returncode == 0 and "intact" in info.stdout, info.stdout + info.stderr

            filler.unlink()  # space is freed
            t_free = time.monotonic()
            t_resumed, resumed = watch.wait_diag(RECORDING_RESUMED, pipeline, after=t_free)
            assert f"recording resumed in {disk / 's-001.mcap'} after" in resumed.message
            dropped = int(re.search(r": (\d+) messages not recorded", resumed.message).group(1))  # type: ignore[union-attr]
            assert dropped > 0
            time.sleep(2.0)
            assert_arm_keeps_its_task(*watch.since(t_resumed))
        finally:
            code = pipeline.stop("up", sig=signal.SIGTERM)
            sub.undeclare()
    out = pipeline.log("up")
    assert code == 0, out[-4000:]
    assert "Traceback" not in out
    assert "exited unexpectedly" not in out  # no service exited, the recorder neither
    assert f"NOT RECORDED: {dropped} messages over" in out
    part1 = pipeline.run("info", str(disk / "s-001.mcap"))
    assert part1.returncode == 0 and "intact" in part1.stdout, part1.stdout + part1.stderr
    assert sorted(p.name for p in disk.iterdir()) == ["s-001.mcap", "s.mcap"]  # no reserve left behind
    print(f"\nfull disk: {failed.message}\nresumed {t_resumed - t_free:.2f} s after the space was freed: "
          f"{resumed.message}\n{len(watch.since(t_fail)[0])} robot states while it ran")


def test_a_read_only_directory_at_the_start_is_reported_and_recording_starts_once_writable(
        tmpfs: Any, pipeline: Pipeline) -> None:
    disk = tmpfs("size=4m,ro")
    output = disk / "sessions" / "s.mcap"
    watch = Watch()
    with pipeline.session() as session:
        sub = session.declare_subscriber(f"{keys.prefix(ROBOT)}/**", watch)
        pipeline.start("up", "up", "--output", str(output))
        try:
            watch.wait_moving(pipeline)  # the pipeline started: the recorder did not hold it back
            t_start = time.monotonic()
            _, not_writing = watch.wait_diag(NOT_WRITING, pipeline)
            assert "read-only file system (Read-only file system, EROFS)" in not_writing.message
            assert f"remount {disk / 'sessions'}/ read-write" in not_writing.message
            time.sleep(WATCH_S)
            assert_arm_keeps_its_task(*watch.since(t_start))
            text = nwr_status(pipeline)
            print(text)
            assert "recorder: not writing" in text and "read-only file system" in text

            remount(disk, "rw")
            t_rw = time.monotonic()
            t_resumed, resumed = watch.wait_diag(RECORDING_RESUMED, pipeline, after=t_rw)
            assert f"recording resumed in {output} after" in resumed.message  # the session's first file
            time.sleep(2.0)
        finally:
            code = pipeline.stop("up", sig=signal.SIGTERM)
            sub.undeclare()
    out = pipeline.log("up")
    assert code == 0, out[-4000:]
    assert "Traceback" not in out and "exited unexpectedly" not in out
    info = pipeline.run("info", str(output))
    assert info.returncode == 0 and "intact" in info.stdout, info.stdout + info.stderr
    print(f"\nread-only at the start: {not_writing.message}\nresumed {t_resumed - t_rw:.2f} s after the "
          f"remount: {resumed.message}")


def test_the_launcher_does_not_wait_for_a_recorder_that_exited_at_its_start(caplog: pytest.LogCaptureFixture
                                                                          ) -> None:
    from nwr.common.config import Profile
    from nwr.services.pipeline import supervisor

    profile = Profile()
    profile.zenoh.base_port = free_base_port()  # nobody there
    gone = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    gone.wait()
    with caplog.at_level("WARNING", logger="nwr"):
        supervisor.wait_for_recorder(profile, gone, timeout_s=WAIT_S)
    assert "the recorder exited at its start (code 3): starting the other services without it" in caplog.text
    assert "not alive after" not in caplog.text
