"""The recorder's disk: a session in parts, and a disk that fills, turns read-only or vanishes.

A session may be split into parts by size or duration
(:class:`SessionRecorder`): every part is a complete MCAP file (an
:class:`nwr.common.recordings.McapRecorder`) with its own schemas, channels
and session metadata (plus its part number).

A disk that fills, turns read-only or vanishes never stops a session: an
OSError of a part's file is held by :class:`GuardedStream` (so that mcap's
writer stays consistent with the bytes it handed over), the part is finished
with the space a :class:`SpaceReserve` kept for it (else cut back to its last
complete chunk, for ``nwr recover``), messages are counted and dropped, and a
new part (``<stem>-NNN.mcap``) is tried every :data:`RETRY_NS` until it can
be written (:class:`SessionRecorder`, :class:`PartFiles`).

Nothing here imports Zenoh or reads a clock: times come in as arguments.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol, cast

from nwr.common.recordings import (
    SESSION_METADATA,
    GapCounter,
    McapRecorder,
    RecordingError,
    publisher_of,
)


@dataclass(frozen=True)
class SplitPolicy:
    """When to start a new part of a session (0 = never)."""

    max_bytes: int = 0
    max_duration_ns: int = 0

    @property
    def enabled(self) -> bool:
        return self.max_bytes > 0 or self.max_duration_ns > 0


def part_path(base: Path, part: int, split: bool) -> Path:
    """``<session>.mcap`` for an unsplit session, ``<session>-NNN.mcap`` for its parts."""
    if not split:
        return base
    return base.with_name(f"{base.stem}-{part:03d}{base.suffix or '.mcap'}")


@dataclass
class PartReport:
    part: int
    messages: int  # in the file (a part cut back to its last complete chunk: those in it)
    first_log_ns: int
    last_log_ns: int
    file: str = ""
    # "finished": a valid file; "cut": ends at its last complete chunk (`nwr recover` it); "torn": ends
    # inside a record (`nwr recover` it); "gone": deleted while it was written.
    outcome: str = "finished"
    reserve_used: bool = False  # finished in the space held in reserve, after a write failed


@dataclass
class Outage:
    """A time the session could not write: which file failed, why, what was not recorded, where it went on."""

    file: str
    reason: str
    since_ns: int | None  # when it stopped writing (None: at the start, before any time was known)
    dropped: int = 0  # messages received and not recorded
    first_dropped_ns: int | None = None
    last_dropped_ns: int | None = None
    seconds: float | None = None  # from the failure to the resume (or to the end of the session)
    resumed_in: str = ""  # the file it went on in ("" : it did not before the end)

    def format(self) -> str:
        span = f" over {self.seconds:.1f} s" if self.seconds is not None else ""
        where = f", resumed in {self.resumed_in}" if self.resumed_in else ", not resumed before the end"
        return f"{self.file}: {self.reason}: {self.dropped} messages not recorded{span}{where}"


@dataclass
class SessionReport:
    """What a session wrote, for the exit log."""

    parts: list[PartReport]
    messages: dict[str, int]
    gaps: dict[str, int]
    restarts: dict[str, int]
    dropped: int = 0  # received while the session could not write: not recorded
    lost: int = 0  # accepted into a part that could not be finished, and not written into a later one
    outages: list[Outage] = field(default_factory=list)

    def format(self) -> str:
        total = sum(self.messages.values())
        gaps = {k: v for k, v in self.gaps.items() if v}
        restarts = {k: v for k, v in self.restarts.items() if v}
        text = (f"{total} messages on {len(self.messages)} channels in {len(self.parts)} file(s); "
                f"sequence gaps: {', '.join(f'{k} {v}' for k, v in gaps.items()) if gaps else 'none'}")
        if restarts:
            text += f"; publisher restarts: {', '.join(f'{k} {v}' for k, v in restarts.items())}"
        if self.outages:
            seconds = sum(o.seconds or 0.0 for o in self.outages)
            text += (f"; NOT RECORDED: {self.dropped} messages over {seconds:.1f} s in {len(self.outages)} "
                     f"time(s) the disk could not be written ({'; '.join(o.format() for o in self.outages)})")
        if self.lost:
            text += f"; {self.lost} messages lost from a file that could not be finished"
        return text


# -- writing on a disk that may fill ------------------------------------------------
# How often a session that cannot write tries a new part, ns.
RETRY_NS = 1_000_000_000
# The space reserve (see SessionRecorder): a chunk and its message indexes are taken to be at most twice the
# largest written so far, and at least this, bytes.
CHUNK_ALLOWANCE = 32 * 1024
# The reserve grows in steps of this many bytes (one allocation per step, not per chunk), and is that much
# above the estimate, which is not a measurement.
RESERVE_STEP = 16 * 1024
# Codes on diag/<recorder>: the part being written failed; still not writing (once per retry); writing again.
# `nwr status` shows them.
WRITE_FAILED = "write_failed"
NOT_WRITING = "not_writing"
RECORDING_RESUMED = "recording_resumed"
DISK_CODES = (WRITE_FAILED, NOT_WRITING, RECORDING_RESUMED)

# errno -> (what it means for a recording, what to do about it); {dir} is the directory of the file.
_OS_ERRORS = {
    errno.ENOSPC: ("disk full", "free space on the disk that holds {dir} (move old recordings elsewhere)"),
    errno.EDQUOT: ("disk quota exceeded", "free space within the recorder's user's quota on {dir}, or raise it"),
    errno.EROFS: ("read-only file system", "remount {dir} read-write, or record elsewhere (--output, "
                  "recorder.directory)"),
    errno.EACCES: ("permission denied", "let the recorder's user write to {dir} (chown, chmod), or record "
                   "elsewhere (--output, recorder.directory)"),
    errno.EPERM: ("operation not permitted", "let the recorder's user write to {dir}, or record elsewhere "
                  "(--output, recorder.directory)"),
    errno.ENOENT: ("file or directory gone", "{dir} or the file was removed or unmounted: recreate or remount "
                   "it, or record elsewhere"),
    errno.ENOTDIR: ("not a directory", "something on the path to {dir} is a file: move it, or record "
                    "elsewhere"),
    errno.EISDIR: ("a directory has the file's name", "give --output a file name in {dir}, not a directory"),
    errno.EIO: ("input/output error", "the disk holding {dir} is failing or was removed (see dmesg): check it, "
                "or record elsewhere"),
    errno.EFBIG: ("file too large", "the file system of {dir} limits a file's size: split the session below it "
                  "(recorder.split_size_mb or --split-size)"),
}


def _as_os_error(exc: Exception) -> OSError:
    return exc if isinstance(exc, OSError) else OSError(f"{type(exc).__name__}: {exc}")


def explain_os_error(exc: OSError, file: str | Path) -> tuple[str, str]:
    """What an OSError of a recording's file means, in words (with the errno's name), and what to do."""
    name = errno.errorcode.get(exc.errno, str(exc.errno)) if exc.errno else "no errno"
    meaning, fix = _OS_ERRORS.get(exc.errno or 0, ("the file cannot be written", "check {dir}, or record "
                                                  "elsewhere (--output, recorder.directory)"))
    directory = Path(file).parent
    return f"{meaning} ({exc.strerror or exc}, {name})", fix.format(dir=f"{directory}/")


class GuardedStream:
    """A part's stream as mcap's writer sees it: a write the file refuses is held, not raised.

    mcap's :class:`~mcap.writer.Writer` counts a chunk in its statistics and
    indexes before it writes it: an OSError out of ``write`` would leave a
    writer whose summary describes a chunk the file does not hold, and no
    way to finish the file. Here the bytes the file refused are kept in
    ``pending`` and the error in ``error``; later writes join ``pending``
    (the session stops feeding the writer, so that is at most the rest of
    one chunk, then the summary), and ``tell`` counts them, so that the
    writer's state always matches what it handed over. :meth:`retry` writes
    them once space is freed, which finishes the file as mcap wrote it;
    :meth:`cut` truncates the file back to the last :meth:`mark` (the end of
    the last complete chunk) if that fails.

    The underlying stream must not buffer (``open(..., buffering=0)``): only
    then does a failed write say how much of it reached the file.
    """

    def __init__(self, raw: IO[bytes]) -> None:
        self.raw = raw
        self.error: OSError | None = None
        self.pending = bytearray()
        self.written = raw.tell()  # bytes in the file
        self.boundary = self.written  # where the file may be cut back to

    def _put(self, data: bytes | bytearray | memoryview) -> int:
        """Write ``data`` to the file, a short write continued; how much reached it (OSError: ``error``)."""
        done = 0
        # Released on the way out: ``data`` may be ``pending`` itself, which is resized next.
        with memoryview(data) as view:
            try:
                while done < len(view):
                    n = self.raw.write(view[done:])
                    if not n:
                        raise OSError(errno.EIO, "the file took no bytes of a write")
                    done += n
            except OSError as exc:
                self.error = exc.with_traceback(None)  # kept: not with the frames (and buffers) it went through
        self.written += done
        return done

    def write(self, data: bytes | bytearray | memoryview) -> int:
        if self.error is None:
            done = self._put(data)
            if self.error is not None:
                self.pending += data[done:]
        else:
            self.pending += data
        return len(data)

    def tell(self) -> int:
        return self.written + len(self.pending)

    def flush(self) -> None:
        if self.error is None:
            try:
                self.raw.flush()
            except OSError as exc:
                self.error = exc

    def mark(self) -> None:
        """The file is whole up to here (the end of a complete chunk): :meth:`cut` returns to it."""
        if self.error is None:
            self.boundary = self.written

    def retry(self) -> bool:
        """Write the held bytes; True if the file now holds everything written to this stream."""
        self.error = None
        if self.pending:
            done = self._put(self.pending)
            del self.pending[:done]
        self.flush()
        return self.error is None and not self.pending

    def cut(self) -> bool:
        """Truncate the file back to the last :meth:`mark` (freeing a partly written chunk); False if it cannot."""
        self.pending.clear()
        try:
            end = self.raw.seek(0, os.SEEK_END)
            if end > self.boundary:
                self.raw.truncate(self.boundary)
            self.written = min(end, self.boundary)
        except OSError:
            return False
        return True


class SpaceReserve:
    """Disk space held in a file beside the recording, given back when the disk fills to finish the part.

    Allocated with ``posix_fallocate`` (zeros written where a file system
    cannot preallocate; on one that compresses them, ZFS say, the reserve
    holds nothing and a full disk leaves the part for ``nwr recover``).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.held = 0

    def hold(self, nbytes: int) -> None:
        """Hold at least ``nbytes``; OSError (the reserve as it was) if the disk does not have them."""
        if nbytes <= self.held:
            return
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            try:
                _allocate(fd, nbytes)
            except OSError:
                os.ftruncate(fd, self.held)  # give back what a partial allocation took
                raise
        finally:
            os.close(fd)
        self.held = nbytes

    def release(self) -> None:
        """Give the space back (remove the file)."""
        self.held = 0
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass  # a read-only or vanished directory: nothing was held there anyway

    def free_bytes(self) -> int:
        """Bytes still free on its file system for an unprivileged user, beside the reserve."""
        st = os.statvfs(self.path.parent)
        return st.f_bavail * st.f_frsize


def _allocate(fd: int, nbytes: int) -> None:
    try:
        os.posix_fallocate(fd, 0, nbytes)
        return
    except AttributeError:
        pass  # not on this platform
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise
    size = os.fstat(fd).st_size
    block = b"\0" * 65536
    os.lseek(fd, size, os.SEEK_SET)
    while size < nbytes:
        size += os.write(fd, block[:nbytes - size])


class PartDisk(Protocol):
    """The file-system side of a session's parts, for :class:`SessionRecorder` (:class:`PartFiles` on disk)."""

    def name(self, part: int) -> str: ...

    def hold(self, nbytes: int, free_after: int = 0) -> None: ...

    def release(self) -> None: ...

    def discard(self, part: int, stream: IO[bytes]) -> None: ...

    def check(self, part: int, stream: IO[bytes]) -> None: ...


class PartFiles:
    """A session's parts on disk: their names, unbuffered streams and one space reserve beside them.

    Part 0 is ``<base>`` (``<stem>-000.mcap`` if the session is split); every
    later part is ``<stem>-NNN.mcap`` (:func:`part_path`): a session that was
    not split becomes split from the first new file a write failure starts.
    The reserve is ``.<base name>.reserve`` in the same directory, removed at
    the end of the session.
    """

    def __init__(self, base: Path, split: bool) -> None:
        self.base = base
        self.split = split
        self.reserve = SpaceReserve(base.with_name(f".{base.name}.reserve"))

    def path(self, part: int) -> Path:
        return part_path(self.base, part, self.split or part > 0)

    def name(self, part: int) -> str:
        return str(self.path(part))

    def open(self, part: int) -> IO[bytes]:
        """The part's file, created (with its directory) and unbuffered (see :class:`GuardedStream`)."""
        path = self.path(part)
        path.parent.mkdir(parents=True, exist_ok=True)
        return path.open("wb", buffering=0)

    def close(self, _part: int, stream: IO[bytes]) -> None:
        stream.close()

    def discard(self, part: int, stream: IO[bytes]) -> None:
        """Close and remove a part that could not even take its header."""
        try:
            stream.close()
            self.path(part).unlink(missing_ok=True)
        except OSError:
            pass  # what could not be written cannot be removed either: `nwr info` says it is empty

    def hold(self, nbytes: int, free_after: int = 0) -> None:
        """Hold ``nbytes`` in reserve, and see ``free_after`` bytes still free beside it (else OSError ENOSPC)."""
        self.base.parent.mkdir(parents=True, exist_ok=True)
        self.reserve.hold(nbytes)
        free = self.reserve.free_bytes() if free_after else 0
        if free < free_after:
            self.reserve.release()
            raise OSError(errno.ENOSPC, f"only {free // 1024} KiB free beside the {nbytes // 1024} KiB reserve, "
                                        f"{free_after // 1024} KiB needed to go on writing")

    def release(self) -> None:
        self.reserve.release()

    def check(self, part: int, stream: IO[bytes]) -> None:
        """OSError ENOENT if the part's name no longer leads to the file being written (deleted, unmounted)."""
        here = os.fstat(stream.fileno())
        try:
            there = os.stat(self.path(part))
        except FileNotFoundError:
            there = None
        if there is None or (there.st_dev, there.st_ino) != (here.st_dev, here.st_ino):
            raise FileNotFoundError(errno.ENOENT, "deleted (or its directory removed) while it was written")


class SessionRecorder:
    """A recording session: one MCAP file, or parts split by size or duration.

    ``open_part(n)`` returns the stream of part ``n`` and ``close_part(n,
    stream)`` is called once that part is finished, so the adapter owns the
    files and the tests can use memory. Every part gets the session metadata
    with ``part`` set; schemas and channels are registered again in each.

    A part is closed before the first message that would make it span
    ``max_duration_ns`` of log time, or once it holds ``max_bytes`` on the
    stream (checked per message; the chunk in memory is not counted, so a part
    may exceed the size by up to one chunk and its summary).

    No OSError of a part's file leaves :meth:`write`, :meth:`flush_if_due` or
    :meth:`finish` (each part is written through a :class:`GuardedStream`):

    - ``disk`` (:class:`PartFiles`) holds a space reserve for the current
      part: about twice its largest chunk plus what finishing it writes
      (:meth:`McapRecorder.finish_bytes`), grown as the part grows. A write
      that fails (or a reserve that cannot grow) ends the part: the reserve
      is given back and the part finished in that space, a valid file with
      every message it had taken. If even that fails, the file is cut back to
      its last complete chunk (``nwr recover`` makes it valid) and the
      messages of the chunk that was in memory are kept, to be written first
      into the next part.
    - While it cannot write, a message is counted (``dropped``, and in the
      gap counter, so that the resume is no gap) and dropped: nothing grows.
    - :meth:`retry_if_due`, every ``retry_ns``, tries the next part: the
      reserve with as much again free beside it, then the file and its header
      (a file that cannot take its header is removed). So a nearly full disk
      does not start a file per retry.
    - ``diag(level, code, text)`` reports each step: :data:`WRITE_FAILED`
      once per failure, :data:`NOT_WRITING` at every failed retry,
      :data:`RECORDING_RESUMED`.
    - The file being written is checked at every chunk (``disk.check``): one
      deleted under the recorder ends its part like a write that fails.

    A session whose first part cannot be created starts without one, in the
    same state (its first part is then ``<base>`` once it can be written).
    """

    def __init__(
        self,
        open_part: Callable[[int], IO[bytes]],
        close_part: Callable[[int, IO[bytes]], None],
        robot: str,
        session_metadata: dict[str, str],
        *,
        compression: str = "zstd",
        chunk_size: int = 256 * 1024,
        chunk_interval_ns: int = 0,
        split: SplitPolicy = SplitPolicy(),
        disk: PartDisk | None = None,
        retry_ns: int = RETRY_NS,
        diag: Callable[[str, str, str], None] | None = None,
    ) -> None:
        self._open_part = open_part
        self._close_part = close_part
        self.robot = robot
        self.session_metadata = dict(session_metadata)
        self.compression = compression
        self.chunk_size = chunk_size
        self.chunk_interval_ns = chunk_interval_ns
        self.split = split
        self.disk = disk
        self.retry_ns = retry_ns
        self._diag = diag
        self.gaps = GapCounter()
        self.parts: list[PartReport] = []
        self.messages: dict[str, int] = {}
        self.current: McapRecorder | None = None
        self.trouble: Outage | None = None  # set while the session cannot write
        self.outages: list[Outage] = []
        self.dropped = 0
        self.lost = 0
        self.finished = False
        self._part_started_ns: int | None = None
        self._stream: GuardedStream | None = None
        self._raw: IO[bytes] | None = None
        self._boundary = 0  # the stream's position after its last complete chunk
        self._committed = 0  # messages of the current part in complete chunks
        self._records = 0  # record groups (chunks, metadata) the current part wrote
        self._largest_write = 0  # bytes of the largest chunk with its indexes so far
        self._reserve = 0  # bytes the disk holds for the current part
        self._reserve_hint = 0  # the most a part needed so far: where the next one starts
        self._unsaved: list[tuple[str, Any, int]] = []  # the messages of the chunk in memory
        self._carried: list[tuple[str, Any, int]] = []  # those of a part that was cut, for the next one
        self._last_try_ns: int | None = None
        try:
            self._start_part()
        except OSError as exc:
            self._stopped(exc, self._name(0), None, "")

    # -- parts ------------------------------------------------------------------
    def _name(self, part: int) -> str:
        return self.disk.name(part) if self.disk is not None else f"part {part}"

    def _reserve_needed(self) -> int:
        chunk = max(CHUNK_ALLOWANCE, 2 * self._largest_write)
        summary = self.current.finish_bytes(self._records) if self.current is not None else 0
        need = chunk + summary + RESERVE_STEP
        return -(-need // RESERVE_STEP) * RESERVE_STEP

    def _start_part(self) -> None:
        """Open the next part and write its header; OSError (nothing left behind) if the disk does not let it."""
        part = len(self.parts)
        if self.disk is not None:
            # What the last part needed is the best guess for this one (its channels come back).
            need = max(self._reserve, self._reserve_hint, self._reserve_needed())
            self.disk.hold(need, free_after=need)
            self._reserve = need
        try:
            raw = self._open_part(part)
        except OSError:
            self._release()
            raise
        stream = GuardedStream(raw)
        try:
            recorder = McapRecorder(cast(IO[bytes], stream), self.robot, compression=self.compression,
                                    chunk_size=self.chunk_size, chunk_interval_ns=self.chunk_interval_ns,
                                    gaps=self.gaps)
            recorder.metadata(SESSION_METADATA, {**self.session_metadata, "part": str(part)})
            # The header and the session metadata reach the OS at once: even a
            # part killed before its first chunk names its session.
            recorder.flush()
        except Exception:
            self._close_part(part, raw)
            self._release()
            raise
        if stream.error is not None:
            if self.disk is not None:
                self.disk.discard(part, raw)
            else:
                self._close_part(part, raw)
            self._release()
            raise stream.error
        stream.mark()
        self.current, self._stream, self._raw = recorder, stream, raw
        self._boundary = stream.tell()
        self._committed = 0
        self._records = 1
        self._unsaved = []
        self.parts.append(PartReport(part, 0, 0, 0, file=self._name(part)))
        self._part_started_ns = None

    def _release(self) -> None:
        if self.disk is not None:
            self.disk.release()
        self._reserve_hint = max(self._reserve_hint, self._reserve)
        self._reserve = 0

    def _end_part(self, cause: OSError | None = None) -> OSError | None:
        """Finish the current part as far as its disk allows; the OSError that stopped it, if any."""
        recorder, stream, raw = self.current, self._stream, self._raw
        assert recorder is not None and stream is not None and raw is not None
        self.current = self._stream = self._raw = None
        report = self.parts[-1]
        if cause is not None:
            # The reserve was held for this: the last chunk, the summary and the footer.
            self._release()
        # With a failed stream, mcap writes the rest of the file into its held bytes.
        broken: Exception | None = None
        try:
            recorder.finish()
        except Exception as exc:  # noqa: BLE001 - mcap's own failure must not end the session either
            broken = exc
        error = cause or stream.error
        outcome = "finished"
        if cause is not None and cause.errno == errno.ENOENT:
            outcome = "gone"
        elif broken is not None:
            # What mcap wrote of its summary is not to be trusted: back to the last complete chunk.
            error = error or OSError(f"mcap could not finish it ({broken!r})")
            outcome = "cut" if stream.cut() else "torn"
        elif stream.error is not None:
            self._release()
            if not stream.retry():
                outcome = "cut" if stream.cut() else "torn"
        try:
            self._close_part(report.part, raw)
        except OSError as exc:  # a network file system may say only now
            error = error or exc
        report.outcome = outcome
        report.reserve_used = self.disk is not None and error is not None and outcome == "finished"
        report.messages = recorder.message_count if outcome == "finished" else self._committed
        firsts = [s.first_log_ns for s in recorder.channels.values() if s.count]
        report.first_log_ns = min(firsts, default=0)
        report.last_log_ns = max((s.last_log_ns for s in recorder.channels.values()), default=0)
        if outcome in ("cut", "torn"):
            self._carried = self._unsaved  # written first into the next part
        self._unsaved = []
        return error

    def _settle(self, now_ns: int) -> None:
        """After a write or a flush: a failure ends the part; a chunk that reached the file moves the boundary."""
        stream = self._stream
        if stream is None:
            return
        if stream.error is not None:
            self._stop(stream.error, now_ns)
            return
        position = stream.tell()
        if position == self._boundary:
            return
        assert self.current is not None and self._raw is not None
        self._largest_write = max(self._largest_write, position - self._boundary)
        self._boundary = position
        stream.mark()
        self._records += 1
        self._committed = self.current.message_count
        self._unsaved.clear()
        if self.disk is not None:
            try:
                self.disk.check(self.parts[-1].part, self._raw)
                need = self._reserve_needed()
                if need > self._reserve:
                    self.disk.hold(need)  # a disk that cannot give it is as good as full
                    self._reserve = need
            except OSError as exc:
                self._stop(exc, now_ns)

    def _stop(self, exc: OSError, now_ns: int) -> None:
        name = self.parts[-1].file
        error = self._end_part(exc) or exc
        self._stopped(error, name, now_ns, self.parts[-1].outcome)

    def _stopped(self, exc: OSError, name: str, now_ns: int | None, outcome: str, *, retrying: bool = True) -> None:
        """Not writing from now on: say why, what became of the file, and what happens next."""
        reason, fix = explain_os_error(exc, name)
        self.trouble = Outage(name, reason, now_ns)
        self.outages.append(self.trouble)
        self._last_try_ns = now_ns
        report = self.parts[-1] if self.parts else None
        if outcome == "finished" and report is not None:
            what = (f"finished it{' in the space held in reserve' if report.reserve_used else ''} "
                    f"({report.messages} messages, a valid file)")
        elif outcome == "cut" and report is not None:
            what = (f"it ends at its last complete chunk ({report.messages} messages; `nwr recover {name}` makes "
                    f"it a valid file); the {len(self._carried)} messages received since "
                    f"{'go into the next file' if retrying else 'are lost'}")
        elif outcome == "torn" and report is not None:
            what = (f"it could not be cut back to its last complete chunk: `nwr recover {name}` saves its "
                    f"{report.messages} messages in complete chunks; the {len(self._carried)} received since "
                    f"{'go into the next file' if retrying else 'are lost'}")
        elif outcome == "gone" and report is not None:
            what = f"the {report.messages} messages written into it are gone with it"
        else:
            what = "no file was started"
        then = (f"until then messages are counted, not recorded, and {self._name(len(self.parts))} is tried "
                f"every {self.retry_ns / 1e9:g} s" if retrying else "the session ends here")
        self._report("error", WRITE_FAILED, f"not writing: {reason} at {name}; {what}; {fix}; {then}")

    def _report(self, level: str, code: str, text: str) -> None:
        if self._diag is not None:
            self._diag(level, code, text)

    def _drop(self, full_key: str, message: Any, log_time_ns: int) -> None:
        trouble = self.trouble
        assert trouble is not None
        trouble.dropped += 1
        self.dropped += 1
        if trouble.first_dropped_ns is None:
            trouble.first_dropped_ns = log_time_ns
        trouble.last_dropped_ns = log_time_ns
        # Seen, so that the first message written again is no gap: these reached the recorder.
        self.gaps.observe(full_key, publisher_of(message), message.seq)

    # -- the adapter's calls ----------------------------------------------------------
    def write(self, full_key: str, message: Any, log_time_ns: int) -> int:
        """Write one message (into a new part if the current one is full), or count it if no part can be written."""
        if self.finished:
            raise RecordingError("the session is finished: no message can be written after finish()")
        recorder = self.current
        if recorder is not None and self.split.enabled and self._due(recorder, log_time_ns):
            name = self.parts[-1].file
            error = self._end_part()
            if error is not None:
                self._stopped(error, name, log_time_ns, self.parts[-1].outcome)
            else:
                try:
                    self._start_part()
                except Exception as exc:  # noqa: BLE001 - an OSError above all; none may end the session
                    self._stopped(_as_os_error(exc), self._name(len(self.parts)), log_time_ns, "")
            recorder = self.current
        if recorder is None:
            self._drop(full_key, message, log_time_ns)
            return 0
        if self._part_started_ns is None:
            self._part_started_ns = log_time_ns
        self.messages[full_key] = self.messages.get(full_key, 0) + 1
        missing = recorder.write(full_key, message, log_time_ns)
        self._unsaved.append((full_key, message, log_time_ns))
        self._settle(log_time_ns)
        return missing

    def _due(self, recorder: McapRecorder, log_time_ns: int) -> bool:
        if recorder.message_count == 0:
            return False  # never leave an empty part behind
        if self.split.max_duration_ns and self._part_started_ns is not None \
                and log_time_ns - self._part_started_ns >= self.split.max_duration_ns:
            return True
        return bool(self.split.max_bytes) and recorder.size() >= self.split.max_bytes

    def flush_if_due(self, now_ns: int) -> bool:
        if self.current is None or not self.current.flush_if_due(now_ns):
            return False
        self._settle(now_ns)
        return True

    def retry_if_due(self, now_ns: int) -> bool:
        """While not writing, every ``retry_ns``: try the next part; True if the session writes again."""
        trouble = self.trouble
        if trouble is None or self.finished:
            return False
        if self._last_try_ns is None:  # stopped at the start: the clock starts now
            trouble.since_ns = trouble.since_ns if trouble.since_ns is not None else now_ns
            self._last_try_ns = now_ns
            return False
        if now_ns - self._last_try_ns < self.retry_ns:
            return False
        self._last_try_ns = now_ns
        name = self._name(len(self.parts))
        try:
            self._start_part()
        except Exception as exc:  # noqa: BLE001 - an OSError above all; none may end the session
            reason, fix = explain_os_error(_as_os_error(exc), name)
            since = f" for {(now_ns - trouble.since_ns) / 1e9:.0f} s" if trouble.since_ns is not None else ""
            self._report("error", NOT_WRITING,
                         f"not writing{since}: {reason} at {name}; {trouble.dropped} messages not recorded; "
                         f"{fix}; retrying every {self.retry_ns / 1e9:g} s")
            return False
        recorder = self.current
        assert recorder is not None
        self.trouble = None
        trouble.resumed_in = name
        trouble.seconds = (now_ns - trouble.since_ns) / 1e9 if trouble.since_ns is not None else None
        carried, self._carried = self._carried, []
        for full_key, message, log_time_ns in carried:
            recorder.write(full_key, message, log_time_ns, count_gaps=False)
            self._unsaved.append((full_key, message, log_time_ns))
        if carried:
            self._part_started_ns = carried[0][2]
        span = (f" ({(trouble.last_dropped_ns - trouble.first_dropped_ns) / 1e9:.1f} s of them)"
                if trouble.first_dropped_ns is not None and trouble.last_dropped_ns is not None else "")
        after = f" after {trouble.seconds:.1f} s" if trouble.seconds is not None else ""
        carried_text = f"; the {len(carried)} messages of the cut file's last chunk written first" if carried else ""
        self._report("info", RECORDING_RESUMED,
                     f"recording resumed in {name}{after}: {trouble.dropped} messages not recorded{span}"
                     f"{carried_text}")
        self._settle(now_ns)
        return True

    def finish(self, now_ns: int | None = None) -> SessionReport:
        """Finish the part being written (or end the time the session could not write); release the reserve."""
        if not self.finished:
            self.finished = True
            if self.current is not None:
                name = self.parts[-1].file
                error = self._end_part()
                if error is not None:
                    self._stopped(error, name, now_ns, self.parts[-1].outcome, retrying=False)
            trouble = self.trouble
            if trouble is not None:
                if now_ns is not None and trouble.since_ns is not None:
                    trouble.seconds = (now_ns - trouble.since_ns) / 1e9
                self.lost += len(self._carried)
                self._carried = []
            self._release()
        return SessionReport(self.parts, dict(self.messages), self.gaps.gaps(), self.gaps.restarts(),
                             dropped=self.dropped, lost=self.lost, outages=list(self.outages))
