"""The recorder's disk: full, read-only, unwritable or vanished, in memory and on real small file systems.

Most tests run a SessionRecorder on a fake disk (``FakeDisk``: part files and
the space reserve share one capacity; an errno can be forced on every
write), which behaves as a Linux file does when it fills: a short write, then
ENOSPC. The ones marked ``mount`` use a real tmpfs (read-only, or 200 KiB)
mounted for the test: they need root and are skipped, with the reason, where
mounting is not permitted. Running as root, ``chmod 0o555`` stops no write, so
a read-only directory is a read-only mount here, and "cannot create the
directory" is a regular file standing where the directory should be.
"""

from __future__ import annotations

import errno
import io
import os
import subprocess
import tracemalloc
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.recordings import read_recording
from nwr.services.recorder import salvage
from nwr.services.recorder.disk import (
    DISK_CODES,
    NOT_WRITING,
    RECORDING_RESUMED,
    WRITE_FAILED,
    GuardedStream,
    PartFiles,
    SessionRecorder,
    SplitPolicy,
    explain_os_error,
    part_path,
)
from nwr.services.tools import status

ROBOT = "ur10e"
MS = 1_000_000
TRACE = m.Trace(seq=3, stamp_ns=1_000)
COMMAND = keys.key(ROBOT, keys.robot_command("cartesian"))
STATE = keys.key(ROBOT, keys.ROBOT_STATE)
META = {"robot": ROBOT, "session": "s", "start_monotonic_ns": "0", "start_time": "2025-01-01T00:00:00+00:00"}
BASE = Path("rec/s.mcap")


# -- a disk that fills ----------------------------------------------------------------
class FakeFile:
    """An unbuffered file on a FakeDisk: a write that does not fit is cut short, the next one raises."""

    def __init__(self, disk: FakeDisk) -> None:
        self.disk = disk
        self.data = bytearray()
        self.closed = False

    def write(self, data: bytes | memoryview) -> int:
        if self.disk.error is not None:
            raise OSError(self.disk.error, os.strerror(self.disk.error))
        room = self.disk.capacity - self.disk.used()
        if room <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = min(len(data), room)
        self.data += bytes(data[:n])
        return n

    def tell(self) -> int:
        return len(self.data)

    def flush(self) -> None:
        pass

    def seek(self, offset: int, whence: int = 0) -> int:
        assert (offset, whence) == (0, os.SEEK_END)
        return len(self.data)

    def truncate(self, size: int) -> int:
        if self.disk.error == errno.EROFS:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        del self.data[size:]
        return size

    def close(self) -> None:
        self.closed = True


class FakeDisk:
    """``capacity`` bytes shared by the parts and the reserve; ``error``: an errno every write and open raises."""

    def __init__(self, capacity: int, split: bool = False) -> None:
        self.capacity = capacity
        self.split = split
        self.files: dict[int, FakeFile] = {}
        self.reserved = 0
        self.error: int | None = None
        self.broken: Exception | None = None  # raised by open: a bug, not the disk
        self.most_reserved = 0

    def used(self) -> int:
        return sum(len(f.data) for f in self.files.values()) + self.reserved

    def _raise(self) -> None:
        if self.error is not None:
            raise OSError(self.error, os.strerror(self.error))

    # open_part / close_part
    def open(self, part: int) -> FakeFile:
        self._raise()
        if self.broken is not None:
            raise self.broken
        self.files[part] = FakeFile(self)
        return self.files[part]

    def close(self, _part: int, stream: Any) -> None:
        stream.close()

    # PartDisk
    def name(self, part: int) -> str:
        return str(part_path(BASE, part, self.split or part > 0))  # as PartFiles names them

    def hold(self, nbytes: int, free_after: int = 0) -> None:
        self._raise()
        if nbytes > self.reserved:
            if self.used() + nbytes - self.reserved > self.capacity:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.reserved = nbytes
            self.most_reserved = max(self.most_reserved, nbytes)
        if self.capacity - self.used() < free_after:
            self.reserved = 0
            raise OSError(errno.ENOSPC, "not enough free beside the reserve")

    def release(self) -> None:
        self.reserved = 0

    def discard(self, part: int, stream: Any) -> None:
        stream.close()
        del self.files[part]

    def check(self, part: int, stream: Any) -> None:
        if self.files.get(part) is not stream:
            raise FileNotFoundError(errno.ENOENT, "deleted")


def command(seq: int, t: int) -> m.PositionCommand:
    return m.PositionCommand(seq=seq, stamp_ns=t, owner="cartesian", q=[0.1 * (seq % 7)] * 6, trace=TRACE)


def state(seq: int, t: int) -> m.RobotState:
    return m.RobotState(seq=seq, stamp_ns=t, q=[0.01 * (seq % 13)] * 6, dq=[0.0] * 6, status="ok",
                        owner="cartesian", backend="sim")


class Session:
    """A SessionRecorder fed at 100 Hz (a command every step, a state every other), the clock in steps of 10 ms.

    ``disk``: a FakeDisk, or PartFiles for real files (it opens and closes the parts too).
    """

    def __init__(self, disk: Any, **kwargs: Any) -> None:
        self.diags: list[tuple[str, str, str]] = []
        self.written: list[tuple[str, int]] = []  # (topic, seq) in the order handed to the recorder
        self.step = 0
        self.recorder = SessionRecorder(disk.open, disk.close, ROBOT, META, chunk_interval_ns=100 * MS,
                                        disk=disk, diag=lambda *d: self.diags.append(d), **kwargs)

    @property
    def now(self) -> int:
        return self.step * 10 * MS

    def run(self, steps: int) -> None:
        for _ in range(steps):
            self.tick()

    def run_until(self, code: str, limit: int = 10_000) -> None:
        for _ in range(limit):
            if self.codes().count(code):
                return
            self.tick()
        raise AssertionError(f"no {code} after {limit} steps: {self.codes()}")

    def tick(self) -> None:
        t, i = self.now, self.step
        self.recorder.write(COMMAND, command(i, t), t)
        self.written.append((COMMAND, i))
        if i % 2 == 0:
            self.recorder.write(STATE, state(i // 2, t), t)
            self.written.append((STATE, i // 2))
        self.recorder.flush_if_due(t)
        self.recorder.retry_if_due(t)
        self.step += 1

    def codes(self) -> list[str]:
        return [code for _level, code, _text in self.diags]

    def texts(self, code: str) -> list[str]:
        return [text for _level, c, text in self.diags if c == code]


def in_file(data: bytes) -> list[tuple[str, int]]:
    """(topic, seq) of every message a (possibly unfinished) MCAP file holds, in file order."""
    topics: dict[int, str] = {}
    out: list[tuple[str, int]] = []

    def sink(record: Any) -> None:
        if isinstance(record, Channel):
            topics[record.id] = record.topic
        elif isinstance(record, Message):
            out.append((topics[record.channel_id], record.sequence))

    salvage.scan(io.BytesIO(data), "part", sink)
    return out


def assert_one_hole(written: list[tuple[str, int]], kept: list[tuple[str, int]], hole: int) -> int:
    """``kept`` is ``written`` with one run of ``hole`` messages taken out, nothing else; where the run starts."""
    assert len(kept) == len(written) - hole
    start = next((i for i, (a, b) in enumerate(zip(written, kept)) if a != b), len(kept))
    assert kept[:start] == written[:start]
    assert kept[start:] == written[start + hole:]
    return start


# -- a full disk ------------------------------------------------------------------------
def test_full_disk_finishes_the_part_in_its_reserve_counts_drops_and_resumes_in_a_new_split_file() -> None:
    disk = FakeDisk(capacity=160 * 1024)
    s = Session(disk)
    s.run_until(WRITE_FAILED)
    failed_at = len(s.written)
    part0 = disk.files[0]
    assert part0.closed and s.recorder.current is None
    (text,) = s.texts(WRITE_FAILED)
    assert "not writing: disk full (No space left on device, ENOSPC) at rec/s.mcap" in text
    assert "finished it in the space held in reserve" in text and "a valid file" in text
    assert "free space on the disk that holds rec/" in text and "rec/s-001.mcap is tried every 1 s" in text
    # The part is a finished, valid MCAP file with every message handed over before the failure.
    report = salvage.scan(io.BytesIO(bytes(part0.data)), "part 0")
    assert report.intact, report.lost
    assert in_file(bytes(part0.data)) == s.written[:failed_at]
    assert disk.reserved == 0  # given back to finish the file

    s.run(300)  # 3 s on a full disk: counted, not written; reported once per retry, not per message
    assert s.codes().count(NOT_WRITING) == 3
    assert "not writing for 3 s: disk full" in s.texts(NOT_WRITING)[-1]
    assert s.recorder.dropped == len(s.written) - failed_at == 450
    assert len(disk.files) == 1  # no empty file left by the retries

    disk.capacity += 4 * 1024 * 1024  # space is freed
    s.run(100)
    (resumed,) = s.texts(RECORDING_RESUMED)
    assert resumed.startswith("recording resumed in rec/s-001.mcap after ")
    dropped = s.recorder.dropped
    assert f": {dropped} messages not recorded" in resumed
    s.run(50)
    final = s.recorder.finish(s.now)

    part1 = bytes(disk.files[1].data)
    assert salvage.scan(io.BytesIO(part1), "part 1").intact
    assert assert_one_hole(s.written, in_file(bytes(part0.data)) + in_file(part1), dropped) == failed_at
    assert final.dropped == dropped and final.lost == 0
    assert [p.file for p in final.parts] == ["rec/s.mcap", "rec/s-001.mcap"]
    assert [p.outcome for p in final.parts] == ["finished", "finished"] and final.parts[0].reserve_used
    assert not any(final.gaps.values()) and not any(final.restarts.values())  # the hole is no gap
    (outage,) = final.outages
    assert outage.resumed_in == "rec/s-001.mcap" and outage.dropped == dropped and outage.seconds is not None
    text = final.format()
    assert f"NOT RECORDED: {dropped} messages over" in text and "disk full" in text
    assert disk.reserved == 0


def test_a_part_that_cannot_be_finished_is_cut_back_to_its_last_chunk_and_its_open_chunk_moves_on() -> None:
    disk = FakeDisk(capacity=1 << 30)
    s = Session(disk)
    s.run(205)  # chunks every 0.1 s; the last 0.04 s in memory
    disk.error = errno.EROFS  # the file system turns read-only: no write, no truncate, no reserve helps
    s.run_until(WRITE_FAILED)
    (text,) = s.texts(WRITE_FAILED)
    assert "read-only file system (Read-only file system, EROFS) at rec/s.mcap" in text
    assert "remount rec/ read-write" in text
    assert "it ends at its last complete chunk" in text and "`nwr recover rec/s.mcap` makes it a valid file" in text
    assert "received since go into the next file" in text
    part0 = bytes(disk.files[0].data)
    scanned = salvage.scan(io.BytesIO(part0), "part 0")
    assert not scanned.footer and not scanned.bad_chunks and scanned.tail is not None and scanned.tail.size == 0
    saved = in_file(part0)  # everything up to the last complete chunk, for `nwr recover`
    assert saved == s.written[:len(saved)] and len(s.written) - len(saved) < 30

    s.run(150)
    assert s.codes().count(NOT_WRITING) == 1  # 1.5 s: one retry so far
    disk.error = None  # remounted read-write
    s.run(150)
    assert s.codes().count(RECORDING_RESUMED) == 1
    assert "messages of the cut file's last chunk written first" in s.texts(RECORDING_RESUMED)[0]
    final = s.recorder.finish(s.now)
    part1 = in_file(bytes(disk.files[1].data))
    # The chunk in memory at the failure is in the next file: only what arrived while not writing is missing.
    assert_one_hole(s.written, saved + part1, final.dropped)
    assert final.parts[0].outcome == "cut" and final.parts[0].messages == len(saved)
    assert not any(final.restarts.values()) and not any(final.gaps.values())


def test_a_full_disk_at_the_very_end_still_gives_a_valid_file() -> None:
    disk = FakeDisk(capacity=1 << 30)
    s = Session(disk)
    s.run(250)
    disk.capacity = disk.used()  # nothing left but the reserve
    final = s.recorder.finish(s.now)
    data = bytes(disk.files[0].data)
    assert salvage.scan(io.BytesIO(data), "part 0").intact
    assert in_file(data) == s.written
    (text,) = s.texts(WRITE_FAILED)
    assert "in the space held in reserve" in text and "the session ends here" in text
    assert final.parts[0].reserve_used and final.dropped == 0


def test_the_reserve_follows_the_part_and_a_reserve_that_cannot_grow_ends_it() -> None:
    disk = FakeDisk(capacity=1 << 30)
    s = Session(disk)
    s.run(50)
    first = disk.reserved
    s.run(3000)  # 30 s: chunk indexes pile up in the summary to come
    assert disk.reserved > first
    disk.capacity = disk.used()  # the next step of the reserve does not fit
    s.run_until(WRITE_FAILED, limit=6000)
    data = bytes(disk.files[0].data)
    assert salvage.scan(io.BytesIO(data), "part 0").intact
    assert in_file(data) == s.written[:len(in_file(data))]


def test_while_not_writing_nothing_grows_and_the_start_itself_may_fail() -> None:
    disk = FakeDisk(capacity=1 << 30)
    disk.error = errno.EACCES
    s = Session(disk)  # the first file cannot be created: no exception, a session that counts
    (text,) = s.texts(WRITE_FAILED)
    assert "permission denied (Permission denied, EACCES) at rec/s.mcap; no file was started" in text
    assert "let the recorder's user write to rec/" in text and "rec/s.mcap is tried every 1 s" in text
    s.run(10)
    tracemalloc.start()
    try:
        s.run(5000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    written_here = 7500
    assert s.recorder.dropped == len(s.written) == written_here + 15
    # (topic, seq) of what the test wrote is kept by the test itself: about 100 bytes each; the recorder adds nothing.
    assert peak < 200 * written_here
    assert len(s.texts(NOT_WRITING)) == 50  # once per retry
    disk.error = None
    s.run(100)
    assert s.recorder.parts[0].file == "rec/s.mcap"  # the session's first file keeps its name
    final = s.recorder.finish(s.now)
    assert_one_hole(s.written, in_file(bytes(disk.files[0].data)), final.dropped)


def test_a_split_session_goes_on_numbering_its_parts() -> None:
    disk = FakeDisk(capacity=1 << 30, split=True)
    s = Session(disk, split=SplitPolicy(max_duration_ns=1_000 * MS))
    s.run(250)
    assert len(disk.files) == 3
    disk.error = errno.EIO
    s.run_until(WRITE_FAILED)
    assert "input/output error" in s.texts(WRITE_FAILED)[0]
    disk.error = None
    s.run(200)
    final = s.recorder.finish(s.now)
    assert [p.file for p in final.parts] == [f"rec/s-{n:03d}.mcap" for n in range(5)]
    assert final.outages[0].file == "rec/s-002.mcap" and final.outages[0].resumed_in == "rec/s-003.mcap"
    kept = [msg for part in sorted(disk.files) for msg in in_file(bytes(disk.files[part].data))]
    assert_one_hole(s.written, kept, final.dropped)


def test_any_failure_to_start_a_part_is_reported_and_retried_not_raised() -> None:
    disk = FakeDisk(capacity=1 << 30)
    s = Session(disk, split=SplitPolicy(max_duration_ns=500 * MS))
    s.run(40)
    disk.broken = RuntimeError("a bug in opening the file")
    s.run(60)  # the split at 0.5 s cannot open its part
    assert "the file cannot be written (RuntimeError: a bug in opening the file, no errno)" in s.texts(WRITE_FAILED)[0]
    s.run(100)
    assert "RuntimeError" in s.texts(NOT_WRITING)[0]
    disk.broken = None
    s.run(100)
    final = s.recorder.finish(s.now)
    kept = [msg for part in sorted(disk.files) for msg in in_file(bytes(disk.files[part].data))]
    assert_one_hole(s.written, kept, final.dropped)


# -- the stream that holds errors ---------------------------------------------------
def test_guarded_stream_holds_a_short_write_and_cuts_back_to_its_mark() -> None:
    disk = FakeDisk(capacity=100)
    raw = FakeFile(disk)
    disk.files[0] = raw
    stream = GuardedStream(raw)  # type: ignore[arg-type]
    stream.write(b"a" * 40)
    stream.mark()
    assert stream.write(b"b" * 90) == 90  # 60 reach the file, 30 are held
    assert stream.error is not None and stream.error.errno == errno.ENOSPC
    assert stream.tell() == 130 and len(stream.pending) == 30 and len(raw.data) == 100
    stream.write(b"c" * 5)  # joins the held bytes
    assert not stream.retry()
    disk.capacity = 200
    assert stream.retry() and bytes(raw.data) == b"a" * 40 + b"b" * 90 + b"c" * 5
    disk.capacity = 135
    stream.write(b"d" * 10)
    assert stream.error is not None and stream.cut()
    assert bytes(raw.data) == b"a" * 40  # back to the mark: the partial bytes are freed


def test_errors_are_explained_with_what_to_do() -> None:
    for code, words in [(errno.ENOSPC, "free space"), (errno.EDQUOT, "quota"), (errno.EROFS, "read-write"),
                        (errno.EACCES, "chown"), (errno.ENOENT, "removed or unmounted"), (errno.EIO, "dmesg"),
                        (errno.EFBIG, "split_size_mb"), (errno.ENOTDIR, "is a file"), (errno.EISDIR, "--output")]:
        meaning, fix = explain_os_error(OSError(code, os.strerror(code)), "/data/rec/s.mcap")
        assert errno.errorcode[code] in meaning and words in fix and "/data/rec/" in fix


def test_part_names_from_the_first_new_file_on() -> None:
    files = PartFiles(Path("rec/s.mcap"), split=False)
    assert [files.path(n) for n in (0, 1, 12)] == [Path("rec/s.mcap"), Path("rec/s-001.mcap"),
                                                   Path("rec/s-012.mcap")]
    assert PartFiles(Path("rec/s.mcap"), split=True).path(0) == Path("rec/s-000.mcap")
    assert files.reserve.path == Path("rec/.s.mcap.reserve")


# -- real files -----------------------------------------------------------------------
def real_session(base: Path) -> Session:
    return Session(PartFiles(base, split=False))


def test_a_directory_that_cannot_be_created_is_retried_until_it_can(tmp_path: Path) -> None:
    blocker = tmp_path / "data"
    blocker.write_text("a file where the recordings' directory should be")
    base = blocker / "rec" / "s.mcap"
    s = real_session(base)
    assert "not a directory (Not a directory, ENOTDIR)" in s.texts(WRITE_FAILED)[0]
    s.run(150)
    assert s.codes().count(NOT_WRITING) == 1
    blocker.unlink()
    s.run(150)
    assert s.texts(RECORDING_RESUMED)[0].startswith(f"recording resumed in {base} after ")
    final = s.recorder.finish(s.now)
    records, _ = read_recording(base)  # finished and valid
    assert len(records) == len(s.written) - final.dropped
    assert sorted(p.name for p in base.parent.iterdir()) == ["s.mcap"]  # the reserve is gone


def test_a_file_deleted_while_written_goes_on_in_a_new_one(tmp_path: Path) -> None:
    base = tmp_path / "rec" / "s.mcap"
    s = real_session(base)
    s.run(100)
    assert (tmp_path / "rec" / ".s.mcap.reserve").stat().st_size >= 32 * 1024
    base.unlink()
    s.run_until(WRITE_FAILED)
    assert "file or directory gone" in s.texts(WRITE_FAILED)[0] and "are gone with it" in s.texts(WRITE_FAILED)[0]
    s.run(150)
    final = s.recorder.finish(s.now)
    assert final.parts[0].outcome == "gone"
    records, metadata = read_recording(tmp_path / "rec" / "s-001.mcap")
    assert metadata["session"]["part"] == "1" and records


def remount(where: Path, options: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{options}", str(where)], check=True)


def test_a_real_200k_file_system_fills_the_file_is_finished_and_recording_resumes(tmpfs: Any) -> None:
    where = tmpfs("size=200k")
    base = where / "s.mcap"
    s = real_session(base)
    s.run_until(WRITE_FAILED, limit=100_000)
    failed_at = len(s.written)
    assert "disk full (No space left on device, ENOSPC)" in s.texts(WRITE_FAILED)[0]
    scanned = salvage.info_file(base)
    assert scanned.intact and scanned.messages == failed_at  # finished in the reserve: nothing lost
    s.run(300)
    assert s.codes().count(NOT_WRITING) == 3
    remount(where, "size=4m")
    s.run(200)
    assert s.codes().count(RECORDING_RESUMED) == 1
    final = s.recorder.finish(s.now)
    assert salvage.info_file(where / "s-001.mcap").intact
    kept = in_file(base.read_bytes()) + in_file((where / "s-001.mcap").read_bytes())
    assert assert_one_hole(s.written, kept, final.dropped) == failed_at
    assert sorted(p.name for p in where.iterdir()) == ["s-001.mcap", "s.mcap"]


def test_a_read_only_mount_at_the_start_then_remounted_read_write(tmpfs: Any) -> None:
    where = tmpfs("size=1m,ro")
    base = where / "sub" / "s.mcap"
    s = real_session(base)
    assert "read-only file system (Read-only file system, EROFS)" in s.texts(WRITE_FAILED)[0]
    s.run(250)
    assert s.codes().count(NOT_WRITING) == 2 and "remount" in s.texts(NOT_WRITING)[-1]
    remount(where, "rw")
    s.run(150)
    final = s.recorder.finish(s.now)
    records, _ = read_recording(base)
    assert len(records) == len(s.written) - final.dropped and final.dropped >= 250


# -- nwr status ------------------------------------------------------------------------
def test_status_shows_a_recorder_that_cannot_write() -> None:
    assert status.RECORDER_DISK_CODES == DISK_CODES
    collector = status.StatusCollector(ROBOT)
    text = ("not writing for 12 s: disk full (No space left on device, ENOSPC) at rec/s-001.mcap; 2400 messages not "
            "recorded; free space on the disk that holds rec/ (move old recordings elsewhere); retrying every 1 s")
    diag = m.Diagnostic(seq=4, stamp_ns=1, service="recorder", level="error", code=NOT_WRITING, message=text)
    other = m.Diagnostic(seq=5, stamp_ns=2, service="recorder", level="warning", code="decode_error", message="x")
    codec = keys.codec(keys.diag("recorder"))
    collector.observe(keys.key(ROBOT, keys.diag("recorder")), codec.encode(diag), 0)
    collector.observe(keys.key(ROBOT, keys.diag("recorder")), codec.encode(other), 0)
    report = collector.report(["recorder", "bridge"], 2.0, 0, [])
    assert f"recorder: {text}" in status.format_report(report).splitlines()
    collector.reset()  # a new window without it: the trouble is over
    assert "recorder:" not in status.format_report(collector.report(["recorder"], 2.0, 0, []))
