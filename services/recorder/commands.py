"""The recorder's subcommands of ``nwr``: ``record``, ``info`` and ``recover``."""

from __future__ import annotations

import argparse
import logging
import os
import re
from pathlib import Path
from typing import Any

from nwr.services.profile import profile_for
from nwr.services.recorder import main as recorder_main
from nwr.services.recorder import salvage

log = logging.getLogger(__name__)


def register(subparsers: Any) -> None:
    record = subparsers.add_parser(
        "record", help="run the recorder alone (same as `nwr run recorder`)",
        description="Record every message under nwr/<robot>/ to MCAP until Ctrl-C or SIGTERM. Chunks are closed "
                    "every recorder.chunk_interval_s, so a killed recorder leaves a file `nwr recover` can repair. "
                    "A disk that fills, a directory that is read-only or cannot be created does not stop it: it "
                    "finishes the file it has, says so on diag/recorder (and `nwr status`), counts what it cannot "
                    "record, and goes on in <stem>-NNN.mcap once it can write again (retried every second).",
    )
    recorder_main.add_arguments(record)
    record.set_defaults(handler=_record)

    info = subparsers.add_parser(
        "info", help="print a recording's channels, counts, rates, duration, gaps and metadata",
        description="Describe an MCAP recording. Works on unfinished (crashed) and damaged files too, reading "
                    "up to the first unreadable record. Exit status 0 for an intact file, 1 for an unfinished or "
                    "damaged one (`nwr recover` it), 2 for a file with nothing to describe.",
    )
    info.add_argument("file", help="MCAP recording")
    info.add_argument("--full", action="store_true", help="print long metadata values (the profile) in full")
    info.set_defaults(handler=_info)

    recover = subparsers.add_parser(
        "recover", help="rewrite a damaged recording (no summary, truncated last chunk) into a valid one",
        description="Read a damaged MCAP file front to back up to the first unreadable record and write what "
                    "could be saved to a new valid file, then say how much was saved and what was lost.",
    )
    recover.add_argument("file", help="damaged MCAP recording (left untouched)")
    recover.add_argument("--output", "-o", help="file to write (default: <file stem>-recovered.mcap)")
    recover.set_defaults(handler=_recover)


def _record(args: argparse.Namespace) -> int:
    return int(recorder_main.run(profile_for(args), args) or 0)


def _info(args: argparse.Namespace) -> int:
    report = salvage.info_file(Path(args.file))
    print(salvage.format_info(report, full=args.full))
    return 0 if report.intact else 1


def _recover(args: argparse.Namespace) -> int:
    path = Path(args.file)
    output = Path(args.output) if args.output else salvage.default_recovery_path(path)
    result = salvage.recover_file(path, output)
    print(salvage.format_recovery(result))
    if result.written == 0:
        log.error("no message of %s could be saved", path)
        return 1
    for reserve in stale_reserves(path):
        reserve.unlink(missing_ok=True)
        print(f"removed {reserve}: the dead recorder's space reserve")
    return 0


PART = re.compile(r"(?P<session>.+)-\d{3}")


def stale_reserves(path: Path) -> list[Path]:
    """The space reserve a recorder left beside ``path`` (``.<session>.mcap.reserve``, :class:`PartFiles`) when it
    died, if no process still writes the session (then the reserve is its, and stays)."""
    part = PART.fullmatch(path.stem)
    base = path.with_name(f"{part['session']}{path.suffix}") if part else path
    reserve = base.with_name(f".{base.name}.reserve")
    if not reserve.exists():
        return []
    session = {base.resolve(), *(p.resolve() for p in base.parent.glob(f"{base.stem}-[0-9][0-9][0-9]{base.suffix}"))}
    return [] if open_anywhere(session) else [reserve]


def open_anywhere(files: set[Path]) -> bool:
    """Whether a process of this user holds one of ``files`` open (Linux's /proc; elsewhere: assume so)."""
    proc = Path("/proc")
    if not (proc / "self" / "fd").is_dir():
        return True
    for fd_dir in proc.glob("[0-9]*/fd"):
        try:
            for fd in fd_dir.iterdir():
                try:
                    if Path(os.readlink(fd)) in files:
                        return True
                except OSError:
                    continue
        except OSError:
            continue  # another user's process, or one that ended meanwhile
    return False
