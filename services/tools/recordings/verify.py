"""``nwr verify FILE``: re-run every recorded service over its own recorded inputs and compare, message for message.

Each service journals what it handled, in order, with every clock reading
it made (``journal/<service>``, :mod:`nwr.common.journal`). For each run of
each service found in the recording, this rebuilds the service's wiring
from the configuration its journal carries, feeds it the recorded inputs the
journal names through :class:`~nwr.common.journal.Playback`, and compares
what it publishes with what the recording holds on the service's output keys
in that run: the same messages, bit for bit (their JSON encoding), matched
by sequence number.

A run is *identical* when every output it recorded is re-made exactly; it
*differs* at the first output (or journal entry) where the re-run parts from
the recording; it *cannot be verified* when the recording lacks what the
re-run needs (the journal's first batch, a batch in the middle, an input
message), and the report says which. Outputs the re-run makes that the
recording lacks were lost on the way to the recorder (telemetry may drop)
only where the recorder saw them missing: it counts every gap in each key's
sequence numbers and writes the counts into the file's metadata. Missing
outputs between the first and the last the recording holds on a key, beyond
the gaps the recorder counted there, were removed from the file afterwards:
the run *differs*, naming the key and the first missing sequence number.
Missing outputs before the first or after the last recorded one (which no
gap reveals), and any in a file without gap counts, are counted, not failed.

A journal's configuration is data from the recording, not the user's word:
the only files a re-run reads (the robot description its profile names, and
the URDF and skin file that description names) must be regular files of at
most :data:`MAX_FILE_BYTES` under the recording's own directory or the
project's packaged robot descriptions; anything else (a device such as
``/dev/zero``, a FIFO, a file elsewhere, a link out of those folders) makes
the run *cannot be verified*, naming the file, and nothing of it is read.
"""

from __future__ import annotations

import argparse
import json
import logging
import stat
import tomllib
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, decode_profile
from nwr.common.errors import ConfigError, NwrError
from nwr.common.journal import Divergence, Playback
from nwr.common.recordings import Recorded, read_recording, recording_robot
from nwr.common.robot import ROBOTS_DIR, resolve_description
from nwr.services.pipeline.graph import wiring_for
from nwr.services.wiring import no_diag

NO_JOURNAL = ("it has no journal (journal/<service> channels): it was recorded by an older nwr, by another tool, "
              "or without the services' journals, so its services cannot be re-run")


# The project's packaged robot descriptions (robots/<name>/robot.toml, its URDF and skin file).
PACKAGED_ROBOTS = ROBOTS_DIR
# The largest file a re-run reads (the packaged UR10e's URDF is 8 kB).
MAX_FILE_BYTES = 4 * 1024 * 1024


def _allowed_file(name: str, field: str, roots: Sequence[Path]) -> Path:
    """``name`` resolved (links followed), if it is a regular file of at most MAX_FILE_BYTES under ``roots``;
    else a one-line ConfigError naming ``field`` and the file. Nothing is opened."""
    path = Path(name).resolve()
    if not any(path.is_relative_to(root) for root in roots):
        where = " or ".join(str(root) for root in roots)
        raise ConfigError(f"{field} = {name!r} ({path}) is outside the recording's directory and the project's "
                          f"packaged robot descriptions ({where}): refused, nwr verify reads no file elsewhere; "
                          "copy the robot description beside the recording and point the profile there")
    try:
        info = path.stat()
    except OSError as exc:
        raise ConfigError(f"{field} = {name!r} ({path}) cannot be read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(info.st_mode):
        raise ConfigError(f"{field} = {name!r} ({path}) is no regular file (a device, a FIFO or a directory): "
                          "refused")
    if info.st_size > MAX_FILE_BYTES:
        raise ConfigError(f"{field} = {name!r} ({path}) has {info.st_size} bytes, more than nwr verify reads "
                          f"({MAX_FILE_BYTES}): refused")
    return path


def check_files(profile: Profile, roots: Sequence[Path]) -> None:
    """The files a re-run of ``profile`` reads (its robot description, and the URDF and skin file that one
    names), each checked by :func:`_allowed_file`; the description read within MAX_FILE_BYTES."""
    name = profile.robot.description
    if not name:
        return  # the packaged UR10e
    robot = _allowed_file(str(resolve_description(name)), "robot.description", roots)
    try:
        with robot.open("rb") as stream:
            data = stream.read(MAX_FILE_BYTES + 1)
        doc = tomllib.loads(data[:MAX_FILE_BYTES].decode("utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"robot.description = {name!r} ({robot}) cannot be read as TOML: {exc}") from None
    for key in ("urdf", "skin"):
        value = doc.get(key)
        if isinstance(value, str):
            _allowed_file(str(robot.parent / value), f"{robot}'s {key}", roots)


@dataclass
class RunResult:
    """The verdict on one run of one service."""

    service: str
    run: int  # 1-based, in start order
    runs: int
    verdict: str  # "identical", "differs" or "unverifiable"
    entries: int = 0
    outputs: dict[str, int] = field(default_factory=dict)  # key -> outputs compared
    lost: int = 0  # re-made outputs the recording lacks (lost before the recorder)
    after_journal: int = 0  # recorded outputs after the journal's last batch (the service was killed)
    detail: str = ""

    def format(self) -> str:
        head = f"{self.service:<20s} run {self.run}/{self.runs}  {self.entries:>7d} inputs  "
        if self.verdict == "identical":
            counts = ", ".join(f"{k} {n}" for k, n in sorted(self.outputs.items()))
            extra = []
            if self.lost:
                extra.append(f"{self.lost} re-made outputs not in the recording (lost on the way to the recorder)")
            if self.after_journal:
                extra.append(f"{self.after_journal} recorded outputs after the journal's end (the service was "
                             "killed before it journaled them)")
            more = f"; {'; '.join(extra)}" if extra else ""
            return f"{head}identical: {sum(self.outputs.values())} outputs ({counts}){more}"
        word = "DIFFERS" if self.verdict == "differs" else "cannot be verified"
        return f"{head}{word}: {self.detail}"


@dataclass
class _Run:
    service: str
    run_ns: int
    batches: list[m.Journal]


def _runs(records: Iterable[Recorded]) -> list[_Run]:
    found: dict[tuple[str, int], list[m.Journal]] = defaultdict(list)
    for r in records:
        if isinstance(r.message, m.Journal):
            found[(r.message.service, r.message.run_ns)].append(r.message)
    return [_Run(service, run_ns, sorted(batches, key=lambda b: b.seq))
            for (service, run_ns), batches in sorted(found.items(), key=lambda kv: (kv[0][0], kv[0][1]))]


def _diff(recorded: Any, remade: Any) -> str:
    a, b = msgspec.to_builtins(recorded), msgspec.to_builtins(remade)
    if isinstance(a, dict) and isinstance(b, dict):
        for name in a.keys() | b.keys():
            if a.get(name) != b.get(name):
                return f"field {name!r}: recorded {_short(a.get(name))}, re-run {_short(b.get(name))}"
    return f"recorded {_short(a)}, re-run {_short(b)}"


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 160 else text[:157] + "..."


def _from_service(key: str, message: Any, wiring: Any) -> bool:
    """Whether a recorded output on one of the wiring's keys is this service's (not a replay's or an impostor's)."""
    if isinstance(message, m.SkinPressure):
        return message.source == getattr(getattr(wiring, "cfg", None), "source", "sim")  # the gateway's own skin
    if isinstance(message, (m.PositionCommand, m.VelocityCommand)):
        return message.owner == getattr(wiring, "name", message.owner)
    return True


@contextmanager
def recorded_run_quiet() -> Iterator[None]:
    """No log lines while a service re-runs: they would be the recorded run's (its loop overruns on the recorded
    clock, its reflexes), printed as if they were verify's findings; the comparison reports what differs."""
    previous = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
        yield
    finally:
        logging.disable(previous)


def _missing_batches(run: _Run, holes: list[tuple[m.Journal, m.Journal]]) -> str:
    """Which journal batches of a run the recording lacks, when in the run, and what it means."""
    missing = sum(b.seq - prev.seq - 1 for prev, b in holes)

    def span(prev: m.Journal, b: m.Journal) -> str:
        first, last = prev.seq + 1, b.seq - 1
        seqs = str(first) if first == last else f"{first}-{last}"
        start, end = (prev.stamp_ns - run.run_ns) * 1e-9, (b.stamp_ns - run.run_ns) * 1e-9
        return f"{seqs} ({start:.1f}-{end:.1f} s into the run)"

    shown = ", ".join(span(prev, b) for prev, b in holes[:3]) + (f" and {len(holes) - 3} more gaps" if len(holes) > 3
                                                                  else "")
    return (f"{missing} of its journal batches never reached the recorder: {shown}; the recorder was stalled or its "
            "link dropped then (its log lists the sequence gaps), and a re-run needs every batch, so this run cannot "
            "be re-run (the other services' runs are verified on their own)")


def verify_run(run: _Run, index: dict[tuple[str, int, int], Any], outputs: dict[str, list[Any]], *,
               number: int, runs: int, until_ns: int | None, roots: Sequence[Path] = (PACKAGED_ROBOTS,),
               reported_gaps: dict[str, int] | None = None) -> RunResult:
    """Re-run one service run; ``outputs``: the recording's messages per key, ``until_ns``: the next run's start,
    ``roots``: the folders whose files the re-run may read (:func:`check_files`)."""
    result = RunResult(run.service, number, runs, "unverifiable")
    batches = run.batches
    if batches[0].seq != 0 or not batches[0].config:
        result.detail = (f"the journal's first batch (with the service's configuration) is not in the recording "
                         f"(first: batch {batches[0].seq}): the recorder started after the service")
        return result
    holes = [(prev, b) for prev, b in zip(batches, batches[1:], strict=False) if b.seq != prev.seq + 1]
    if holes:
        result.detail = _missing_batches(run, holes)
        return result
    try:
        config = json.loads(batches[0].config)
        profile = decode_profile(config["profile"], "the journal's profile")
        params = config.get("params", {})
        factory = wiring_for(run.service)
    except (ValueError, KeyError, TypeError, msgspec.ValidationError, ConfigError) as exc:
        result.detail = f"the journal's configuration cannot be read: {exc}"
        return result
    try:
        check_files(profile, roots)
    except ConfigError as exc:
        result.detail = f"the journal's configuration names a file the re-run may not read: {exc}"
        return result
    entries = [e for b in batches for e in b.entries]
    result.entries = len(entries)
    remade: dict[str, dict[int, Any]] = defaultdict(dict)

    def out(key: str, message: Any) -> None:
        remade[key][message.seq] = message

    journal = Playback(entries)
    try:
        with recorded_run_quiet():
            wiring = factory.rebuild(profile, params, journal=journal, out=out, diag=no_diag)
            while (entry := journal.peek()) is not None:
                message = None
                if entry.key:
                    message = index.get((entry.key, entry.seq, entry.stamp_ns))
                    if message is None:
                        result.detail = (f"entry {journal.index + 1} ({entry.input}): its input, {entry.key} seq "
                                         f"{entry.seq} stamped {entry.stamp_ns}, is not in the recording")
                        return result
                wiring.replay(entry, message)
            journal.finish_entry()
    except Divergence as exc:
        result.verdict, result.detail = "differs", str(exc)
        return result
    except ConfigError as exc:
        result.detail = str(exc)
        return result
    except Exception as exc:  # the re-run failed where the live run did not
        result.verdict = "differs"
        result.detail = f"entry {journal.index}: the re-run raised {exc!r} where the live run went on"
        return result
    final = batches[-1].final
    last_ns = max((t for e in entries for t in e.now), default=run.run_ns)
    encode = msgspec.json.encode
    first_diff: tuple[int, str] | None = None
    for key in wiring.outputs:
        mine = remade.get(key, {})
        count = 0
        seen: set[int] = set()
        for message in outputs.get(key, []):
            if message.stamp_ns < run.run_ns or (until_ns is not None and message.stamp_ns >= until_ns) \
                    or not _from_service(key, message, wiring):
                continue
            seen.add(message.seq)
            again = mine.get(message.seq)
            if again is None:
                if not final and message.stamp_ns >= last_ns:
                    result.after_journal += 1
                    continue
                where = (message.stamp_ns, f"{key} seq {message.seq}: recorded, but the re-run did not make it")
            elif encode(again) != encode(message):
                where = (message.stamp_ns, f"{key} seq {message.seq}: {_diff(message, again)}")
            else:
                count += 1
                continue
            if first_diff is None or where[0] < first_diff[0]:
                first_diff = where
        result.outputs[key] = count
        missing = sorted(seq for seq in mine if seq not in seen)
        result.lost += len(missing)
        inside = [seq for seq in missing if seen and min(seen) < seq < max(seen)]
        if reported_gaps is not None and len(inside) > reported_gaps.get(key, 0):
            where = (mine[inside[0]].stamp_ns,
                     f"{key} seq {inside[0]}: re-made but not in the recording, one of {len(inside)} missing between "
                     f"the recorded outputs where the recorder counted {reported_gaps.get(key, 0)} lost: removed "
                     "from the file after it was written")
            if first_diff is None or where[0] < first_diff[0]:
                first_diff = where
    if first_diff is not None:
        result.verdict, result.detail = "differs", f"first at {first_diff[1]}"
    else:
        result.verdict = "identical"
    return result


def recorded_gaps(metadata: dict[str, dict[str, str]]) -> dict[str, int] | None:
    """The sequence gaps the recorder counted per relative key (its ``recording`` metadata); None without them
    (a recovered file, one cut off by a crash, another tool's)."""
    try:
        gaps = json.loads(metadata["recording"]["gaps"])
        robot = recording_robot(metadata)
        out = {}
        for full, n in gaps.items():
            if full.startswith(keys.prefix(robot) + "/"):
                out[keys.relative_key(robot, full)] = int(n)
        return out
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


def verify(path: str | Path) -> list[RunResult]:
    """Every service run of a recording, re-run and compared; ConfigError when there is nothing to verify."""
    records, metadata = read_recording(path)
    runs = _runs(records)
    if not runs:
        raise ConfigError(f"{path}: {NO_JOURNAL}")
    index: dict[tuple[str, int, int], Any] = {}
    outputs: dict[str, list[Any]] = defaultdict(list)
    for r in records:
        if isinstance(r.message, m.Journal):
            continue
        index[(r.key, r.message.seq, r.message.stamp_ns)] = r.message
        outputs[r.key].append(r.message)
    roots = (Path(path).resolve().parent, PACKAGED_ROBOTS)
    gaps = recorded_gaps(metadata)
    results = []
    by_service: dict[str, list[_Run]] = defaultdict(list)
    for run in runs:
        by_service[run.service].append(run)
    for service_runs in by_service.values():
        for i, run in enumerate(service_runs):
            until = service_runs[i + 1].run_ns if i + 1 < len(service_runs) else None
            results.append(verify_run(run, index, outputs, number=i + 1, runs=len(service_runs), until_ns=until,
                                      roots=roots, reported_gaps=gaps))
    return results


def _run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if path.is_dir():
        raise ConfigError(f"{path} is a directory: give an MCAP recording (recordings/<session>.mcap)")
    try:
        results = verify(path)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path} does not exist") from exc
    except NwrError:
        raise
    except Exception as exc:  # mcap's and the OS's errors on a file that is no (complete) recording
        raise ConfigError(f"{path} cannot be read as an MCAP recording ({type(exc).__name__}: {exc}); one cut off "
                          "by a crash can be repaired with `nwr recover`") from exc
    for result in results:
        print(result.format())
    bad = [r for r in results if r.verdict != "identical"]
    print(f"{len(results) - len(bad)} of {len(results)} service runs re-made their recorded outputs bit for bit")
    return 0 if not bad else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "verify", help="re-run each recorded service over its recorded inputs and compare its outputs bit for bit",
        description="Re-run every service of a recording (gateway, gain, planners, bridge) from its journal over "
                    "its own recorded inputs, and report per service run whether its outputs equal the recorded "
                    "ones message for message, and where they first part. Exit status 0 when every run is "
                    "identical, 1 otherwise. The only files a re-run reads (the robot description a journaled "
                    "profile names, its URDF and skin file) must be regular files of at most 4 MiB in the "
                    "recording's directory or among the packaged robot descriptions; anything else makes that run "
                    "'cannot be verified'.")
    p.add_argument("file", help="MCAP recording of a live session (nwr demo, nwr up) or of a lockstep run")
    p.set_defaults(handler=_run)
