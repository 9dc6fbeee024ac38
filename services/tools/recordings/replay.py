"""``nwr replay FILE``: play a recorded touch session again, live or in lockstep.

Three ways, all from the recorded skin stream (``skin/pressure``):

- live, into a running pipeline (``nwr up`` without its gateway, or any
  process speaking the keys): the selected topics are published under
  ``nwr/<robot>/`` with fresh stamps (sequence numbers kept), at ``--speed``,
  between ``--start`` and ``--end``, ``--loop``-ed if asked;
- live against a reflex service (``--reflex NAME`` or ``--planner-cmd CMD``):
  the gain estimator, that planner, the simulated bridge and a recorder are
  started for the replay and stopped after it; the result is a new recording
  to compare with the first (``nwr compare``);
- ``--fast``: the same cores chained in this process on simulated time
  (:mod:`nwr.services.pipeline.lockstep`), as fast as they go, deterministic: the same
  file and strategy give the same messages every run. Several files replay
  at once, each in a process of its own (``--jobs``, default: the CPUs this
  process may use), or on a Dask cluster (``--cluster ADDRESS``: the
  ``cluster`` extra; its workers have nwr installed and share this machine's
  filesystem), each into ``recordings/<FILE>-replay-<reflex>.mcap``, with a
  progress bar.

Replay is open loop by default: a recorded press is replayed as recorded,
even if the new reflex moves the pad away sooner. ``--fast --resimulate``
closes the loop for sessions recorded from the simulated skin, whose
recordings keep each touch's ground truth (``skin/touch``: pad, pressure
profile, contact point) and each sample's touch part (``touch_hpa``): every
sample's touch part is replaced by what the touch presses against the
replay's own arm (the finger stays where it met the pad; the pressure falls
as the pad withdraws from it, over gateway.sim.contact_depth_m), noise and
drift kept as recorded. Sessions of a real skin have no ground truth: only
open-loop replay applies to them. A live replay never re-simulates (use
--fast).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import logging
import multiprocessing
import os
import shlex
import subprocess
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import load_script
from nwr.common.node import Node
from nwr.common.recordings import McapRecorder, Recorded, new_file, read_recording, session_metadata
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.core import NO_GROUND_TRUTH, Resimulator, sim_settings
from nwr.services.pipeline.graph import Layout, process_name, recorder_args, units
from nwr.services.pipeline.supervisor import failed, spawn, stop_all
from nwr.services.planner import strategies
from nwr.services.profile import loosened_safety, profile_for

if TYPE_CHECKING:
    from nwr.services.gateway.stepped import ResimulatedSkin, SkinSource

log = logging.getLogger(__name__)

REPLAYABLE = ("skin/pressure",)


def select(records: list[Recorded], topics: list[str], start_s: float, end_s: float | None) -> list[Recorded]:
    """The records of ``topics`` between ``start_s`` and ``end_s`` (from the recording's first message)."""
    if not records:
        return []
    t0 = records[0].log_time_ns
    lo = t0 + round(start_s * 1e9)
    hi = t0 + round(end_s * 1e9) if end_s is not None else None
    return [r for r in records if r.key in topics and r.log_time_ns >= lo and (hi is None or r.log_time_ns <= hi)]


def restamped(message: Any, stamp_ns: int) -> Any:
    return msgspec.structs.replace(message, stamp_ns=stamp_ns)


def play(node: Node, robot_records: list[Recorded], speed: float, loop: bool, stop: threading.Event) -> int:
    """Publish the records in real time (divided by ``speed``); returns how many were sent."""
    publishers = {key: node.publisher(key) for key in {r.key for r in robot_records}}
    sent = 0
    while True:
        start_wall = time.monotonic_ns()
        first = robot_records[0].log_time_ns
        for record in robot_records:
            due = start_wall + round((record.log_time_ns - first) / speed)
            delay = (due - time.monotonic_ns()) / 1e9
            if delay > 0 and stop.wait(delay):
                return sent
            publishers[record.key](restamped(record.message, node.clock.now_ns()))
            sent += 1
        if not loop or stop.is_set():
            return sent


def resimulated(profile: Profile, records: list[Recorded], chosen: list[Recorded]) -> ResimulatedSkin:
    """The chosen skin samples with the recording's touches re-simulated (ConfigError without ground truth)."""
    from nwr.services.gateway.stepped import ResimulatedSkin

    touches = [r.message for r in records if r.key == keys.SKIN_TOUCH]
    skin = [r.message for r in chosen if r.key == keys.SKIN_PRESSURE]
    if not touches or not skin or any(len(s.touch_hpa) != len(s.absolute_hpa) for s in skin):
        raise ConfigError(NO_GROUND_TRUTH)
    # The sample just before the replayed window, if any: the baseline filter
    # continues from it on the gateway's own clock.
    first = skin[0].stamp_ns
    previous = max((r.message.stamp_ns for r in records
                    if r.key == keys.SKIN_PRESSURE and r.message.stamp_ns < first), default=None)
    desc = load_description(profile.robot.description or None)
    resimulator = Resimulator(profile.gateway, touches, len(desc.pads), previous)
    return ResimulatedSkin(skin, resimulator, RobotModel(desc))


def record_lockstep(profile: Profile, skin: list[m.SkinPressure] | SkinSource, strategy: str, output: Path, *,
                    labels: dict[str, str], touches: list[m.SkinTouch] | None = None,
                    start_time_iso: str = "", start_ns: int | None = None,
                    settle_s: float = 2.0) -> tuple[Path, float, float]:
    """A lockstep run into the recording ``output``; returns it, the simulated and the wall-clock duration.

    Recorded samples given as a list are written as they are, on their own
    timeline, with the recorded ``touches`` that go with them; a source
    writes what it makes.
    """
    from nwr.services.gateway.stepped import SkinSource
    from nwr.services.pipeline.lockstep import Lockstep

    lockstep = Lockstep(profile, strategy=strategy)
    robot = profile.robot.name
    with new_file(output, "the recording") as stream:
        recorder = McapRecorder(stream, robot, compression=profile.recorder.compression,
                                chunk_size=profile.recorder.chunk_size)
        first = (skin.stamp(0) if len(skin) else 0) if isinstance(skin, SkinSource) else \
            (skin[0].stamp_ns if skin else 0)
        recorder.metadata("session", session_metadata(
            robot=robot, session=output.stem, profile_json=msgspec.json.encode(profile).decode(), strategy=strategy,
            planner=strategy, start_time_iso=start_time_iso, start_monotonic_ns=first, labels=labels,
            loosened_safety=loosened_safety(profile), timing="lockstep",
        ))
        if not isinstance(skin, SkinSource):
            for touch in touches or []:
                recorder.write(keys.key(robot, keys.SKIN_TOUCH), touch, touch.stamp_ns)
            for sample in skin:  # the recorded input, on its own timeline
                recorder.write(keys.key(robot, keys.SKIN_PRESSURE), sample, sample.stamp_ns)

        def emit(key: str, message: object, stamp_ns: int) -> None:
            recorder.write(keys.key(robot, key), message, stamp_ns)

        t = time.perf_counter()
        report = lockstep.run(skin, emit, start_ns=start_ns, settle_s=settle_s)
        wall = time.perf_counter() - t
        recorder.finish()
    return output, report.simulated_s, wall


def run_fast(profile: Profile, records: list[Recorded], strategy: str, output: Path,
             source: Path, metadata: dict[str, dict[str, str]], *,
             chosen: list[Recorded] | None = None, resimulate: bool = False) -> tuple[Path, float, float]:
    """Lockstep replay of the ``chosen`` records (default: all) into ``output``; returns it, the simulated and
    the wall-clock duration. ``resimulate``: the simulated skin's touches against the replay's arm.

    A replay that reaches the recording's last skin sample ends there, as the recorded session did (its skin
    went on at rest through its own settle, live or in lockstep); a replay of a window runs on 2 s after it,
    so that its last reflex plays out."""
    chosen = records if chosen is None else chosen
    last = next((r for r in reversed(records) if r.key == keys.SKIN_PRESSURE), None)
    reaches_end = last is not None and any(r is last for r in reversed(chosen))
    labels = {"replay_of": str(source), "replay_mode": "fast"}
    skin: list[m.SkinPressure] | SkinSource
    touches: list[m.SkinTouch] = []
    if resimulate:
        skin = resimulated(profile, records, chosen)
        labels["resimulated"] = "true"
    else:
        skin = [r.message for r in chosen if r.key == keys.SKIN_PRESSURE]
        # The recorded ground truth goes along with the samples it belongs to,
        # so that the replay can itself be re-simulated.
        touches = [r.message for r in records if r.key == keys.SKIN_TOUCH]
    return record_lockstep(profile, skin, strategy, output, labels=labels, touches=touches,
                           start_time_iso=metadata.get("session", {}).get("start_time", ""),
                           start_ns=task_start_ns(records, chosen), settle_s=0.0 if reaches_end else 2.0)


def task_start_ns(records: list[Recorded], chosen: list[Recorded]) -> int | None:
    """When the recorded pipeline's planner sent its first command (its task started), if that was before
    the first skin sample and the replay starts there; None otherwise (the task's phase is unknown then)."""
    first = next((r for r in records if r.key == keys.SKIN_PRESSURE), None)
    window = next((r for r in chosen if r.key == keys.SKIN_PRESSURE), None)
    if first is None or window is not first:
        return None
    command = min((r.message.stamp_ns for r in records if keys.is_command(r.key)), default=None)
    if command is None or command >= first.message.stamp_ns:
        return None
    return command


def simulate(profile: Profile, script_name: str, strategy: str, output: Path) -> tuple[Path, float, float]:
    """A simulated session in lockstep: the simulated skin on a touch script, the cores and the simulated arm
    (``nwr demo --fast``), open or closed loop as ``gateway.sim.closed_loop`` says."""
    from nwr.services.gateway.stepped import SimulatedSkin

    desc = load_description(profile.robot.description or None)
    source = SimulatedSkin(profile, load_script(script_name, profile.robot.description), RobotModel(desc))
    labels = {"simulated": "lockstep", "script": script_name,
              "closed_loop": str(sim_settings(profile.gateway).closed_loop).lower(),
              "world": "physics" if profile.bridge.backend == "physics" else "scripted"}
    # The monotonic stamps are simulated (from SimulatedSkin's origin); the
    # wall-clock start is when the simulation ran.
    return record_lockstep(profile, source, strategy, output, labels=labels,
                           start_time_iso=dt.datetime.now(dt.UTC).isoformat())


def _layout_for(args: argparse.Namespace, output: Path) -> tuple[Layout, str]:
    """What a live replay against a reflex service starts (no gateway: the replay is the skin), and the planner's name.

    With ``--planner-cmd`` the planner is the user's own process: the layout
    has none, and the bridge follows ``--name``.
    """
    name = args.name or args.reflex or "replayed"
    layout = Layout(planners=[] if args.planner_cmd else [name], active=name, gateway=None,
                    recorder=recorder_args(output, output.stem, args.reflex or "external",
                                           {"replay_of": str(args.file[0])}))
    return layout, name


@dataclass(frozen=True)
class FastReplay:
    """What one lockstep replay did."""

    source: Path
    output: Path
    strategy: str
    samples: int  # records replayed (skin samples)
    simulated_s: float
    wall_s: float

    def line(self, resimulated: bool) -> str:
        how = ", touches re-simulated," if resimulated else ""
        return (f"replayed {self.samples} skin samples ({self.simulated_s:.1f} s){how} against {self.strategy!r} in "
                f"lockstep in {self.wall_s:.2f} s ({self.simulated_s / self.wall_s:.0f}x real time): {self.output}")


def _prepare(args: argparse.Namespace, profile: Profile,
             source: Path) -> tuple[list[Recorded], dict[str, dict[str, str]], list[Recorded], str, Path]:
    """The recording read and checked before anything is started (a bad file ends the replay with one line): its
    records, metadata, the records chosen, the strategy and the output."""
    records, metadata = read_recording(source)
    topics = [t for t in (args.topics.split(",") if args.topics else REPLAYABLE) if t]
    bad = [t for t in topics if t not in REPLAYABLE]
    if bad:
        raise ConfigError(f"--topics {bad}: only {list(REPLAYABLE)} can be replayed (the rest is what a replay "
                          "produces anew)")
    chosen = select(records, topics, args.start, args.end)
    if not chosen:
        raise ConfigError(f"{source}: nothing to replay on {topics} between {args.start} s and {args.end} s")
    strategy = args.reflex or metadata.get("session", {}).get("strategy") or profile.planner.strategy
    default_out = Path(profile.recorder.directory) / f"{source.stem}-replay-{args.reflex or 'external'}.mcap"
    output = Path(args.output) if args.output else default_out
    if output.resolve() == source.resolve():
        raise ConfigError(f"-o {output} is the recording being replayed: write the replay to another file")
    if args.resimulate and not args.fast:
        raise ConfigError("--resimulate needs --fast: a live replay publishes the recorded samples as they were "
                          "and cannot re-simulate them against the new arm's motion")
    if args.fast:
        if args.planner_cmd:
            raise ConfigError("--fast runs the project's own cores in this process; "
                              "use a live replay to replay against --planner-cmd")
        if strategy not in strategies.names():
            raise ConfigError(f"strategy {strategy!r} of the recording is not one of {list(strategies.names())}: "
                              "choose one with --reflex")
    return records, metadata, chosen, strategy, output


def replay_fast(args: argparse.Namespace, source: Path) -> FastReplay:
    """One recording replayed in lockstep, as ``args`` ask (``--fast``)."""
    profile = profile_for(args)
    records, metadata, chosen, strategy, output = _prepare(args, profile, source)
    path, simulated, wall = run_fast(profile, records, strategy, output, source, metadata, chosen=chosen,
                                     resimulate=args.resimulate)
    return FastReplay(source, path, strategy, len(chosen), simulated, wall)


def _cluster_jobs(args: argparse.Namespace, sources: list[Path]) -> list[tuple[argparse.Namespace, Path]]:
    """Each replay's arguments and source with every path absolute: a cluster's workers have working directories
    of their own, and read and write through the filesystem they share with this machine."""
    directory = Path(profile_for(args).recorder.directory).resolve()
    jobs = []
    for source in sources:
        one = argparse.Namespace(**vars(args))
        one.output = str(directory / f"{source.stem}-replay-{args.reflex or 'external'}.mcap")
        if args.profile and Path(args.profile).is_file():
            one.profile = str(Path(args.profile).resolve())
        jobs.append((one, source.resolve()))
    return jobs


@contextlib.contextmanager
def _executor(args: argparse.Namespace, count: int) -> Iterator[tuple[Executor, str]]:
    """Where the replays run, and how to say so: the Dask cluster at ``--cluster``, or ``--jobs`` processes here."""
    if not args.cluster:
        jobs = min(args.jobs or len(os.sched_getaffinity(0)), count)
        # spawn: each replay in a fresh interpreter (nothing of this process's state, threads or loaded libraries)
        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            yield pool, f"{jobs} at once"
        return
    if args.jobs:
        raise ConfigError("--jobs counts this machine's processes: a --cluster's scheduler decides how many run "
                          "at once")
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--cluster needs Dask's scheduler client: pip install 'nwr[cluster]'") from None
    try:
        client = Client(args.cluster, timeout=args.cluster_timeout)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"--cluster {args.cluster}: no Dask scheduler answered ({exc})") from exc
    with client:
        workers = len(client.scheduler_info(n_workers=-1).get("workers", {}))
        # pure=False: a file replayed twice (two runs of this command) is two tasks, never a cached result
        yield client.get_executor(pure=False), f"on the Dask cluster at {args.cluster} ({workers} workers)"


def _replay_many(args: argparse.Namespace, sources: list[Path]) -> int:
    """Several recordings in lockstep, each in a process of its own (``--jobs`` at once, or on a Dask
    ``--cluster``), with a progress bar."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if not args.fast:
        raise ConfigError("several recordings replay in lockstep only: add --fast (a live replay plays one file)")
    if args.output:
        raise ConfigError("-o names one replay's recording: with several files each goes to "
                          "<recorder.directory>/<FILE>-replay-<reflex>.mcap")
    stems = [s.stem for s in sources]
    twice = sorted({stem for stem in stems if stems.count(stem) > 1})
    if twice:
        raise ConfigError(f"recordings {twice} are named alike: their replays would write the same file")
    work = _cluster_jobs(args, sources) if args.cluster else [(args, source) for source in sources]
    done: list[FastReplay] = []
    failed_files: list[str] = []
    t0 = time.perf_counter()
    with _executor(args, len(sources)) as (pool, where), \
            Progress(TextColumn("replaying"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                     transient=True) as progress:
        task = progress.add_task("replay", total=len(sources))
        futures = {pool.submit(replay_fast, one, source): source for one, source in work}
        for future in as_completed(futures):
            source = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001  one bad file must not lose the others' replays
                failed_files.append(str(source))
                progress.console.print(f"{source}: not replayed: {exc}")
            else:
                done.append(result)
                progress.console.print(result.line(args.resimulate))
            progress.advance(task)
    wall = time.perf_counter() - t0
    simulated = sum(r.simulated_s for r in done)
    print(f"{len(done)} of {len(sources)} recordings ({simulated:.1f} s) replayed in lockstep in {wall:.2f} s, "
          f"{where} ({simulated / wall:.0f}x real time in all)"
          + (f"; not replayed: {', '.join(failed_files)}" if failed_files else ""))
    return 1 if failed_files else 0


def _run(args: argparse.Namespace) -> int:
    sources = [Path(f) for f in args.file]
    if len(sources) > 1 or args.cluster:
        return _replay_many(args, sources)
    source = sources[0]
    if args.fast:
        print(replay_fast(args, source).line(args.resimulate))
        return 0
    profile = profile_for(args)
    records, metadata, chosen, strategy, output = _prepare(args, profile, source)
    span = (chosen[-1].log_time_ns - chosen[0].log_time_ns) / 1e9

    robot = args.robot or metadata.get("session", {}).get("robot") or profile.robot.name
    procs: dict[str, subprocess.Popen[bytes]] = {}
    codes: dict[str, int] = {}
    try:
        waits: list[str] = []
        if args.reflex or args.planner_cmd:
            layout, name = _layout_for(args, output)
            for unit in units(layout):
                procs[unit.label] = spawn(unit, args.profile, args.log_level)
            if args.planner_cmd:
                procs[process_name("planner", name)] = subprocess.Popen([*shlex.split(args.planner_cmd)])
            waits = [*procs]
        with Node("replay", robot, profile.zenoh, token=False) as node:
            node.install_signal_handlers()
            if waits:
                missing = node.wait_for(waits, timeout_s=30.0)
                if missing:
                    log.error("services %s did not come up within 30 s", missing)
                    return 1
            log.info("replaying %d messages (%.1f s) of %s at %gx%s", len(chosen), span, source, args.speed,
                     ", looping" if args.loop else "")
            sent = play(node, chosen, args.speed, args.loop, node.stop)
            log.info("sent %d messages", sent)
            if procs:
                node.stop.wait(2.0)  # the last reflex returns, the recorder catches up
    finally:
        if procs:
            codes = stop_all(procs)
    # Checked after the finally so that an error of the replay itself is never swallowed.
    errors = failed(codes)
    if errors:
        log.error("services stopped with errors: %s", errors)
        return 1
    if procs:
        print(f"replay against {args.reflex or args.planner_cmd!r} recorded to {output}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="play a recorded session again: live, against any reflex service, or in lockstep",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", nargs="+", help="MCAP recording (several: with --fast, replayed at once)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed factor (live replay; default 1)")
    p.add_argument("--start", type=float, default=0.0, help="start at this offset from the recording's start, s")
    p.add_argument("--end", type=float, default=None, help="stop at this offset from the recording's start, s")
    p.add_argument("--loop", action="store_true", help="start again at the end (live replay without a service)")
    p.add_argument("--topics", help=f"comma-separated topics to replay (default and only choice: {REPLAYABLE[0]})")
    p.add_argument("--robot", help="publish under nwr/<ROBOT>/ (default: the recording's robot)")
    p.add_argument("--reflex", choices=strategies.names(),
                   help="replay against a planner of this strategy with the simulated bridge, into a new recording")
    p.add_argument("--planner-cmd", metavar="CMD",
                   help="replay against this command instead of the project's planner (any process speaking the "
                        "keys; give its planner name with --name), with the simulated bridge, into a new recording")
    p.add_argument("--name", help="name of the planner to replay against (default: the strategy)")
    p.add_argument("--fast", action="store_true",
                   help="lockstep in this process on simulated time, as fast as the cores go; deterministic")
    p.add_argument("--resimulate", action="store_true",
                   help="with --fast, for sessions of the simulated skin: re-simulate each touch's pressure against "
                        "the replay's arm (it falls as the pad withdraws from the finger); sessions of a real skin "
                        "replay open loop only")
    p.add_argument("--output", "-o", help="recording to write (default: recordings/<FILE>-replay-<reflex>.mcap; "
                                          "one file only)")
    p.add_argument("--jobs", "-j", type=int, default=0,
                   help="with --fast and several files: how many replay at once, each in a process of its own "
                        "(default: the CPUs this process may use)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="with --fast: replay on the Dask cluster whose scheduler is at ADDRESS (tcp://HOST:PORT; "
                        "the cluster extra: pip install 'nwr[cluster]'), one task per file; its workers need nwr "
                        "installed and this machine's filesystem (the files are read and the replays written by "
                        "absolute path)")
    p.add_argument("--cluster-timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long to wait for the --cluster scheduler to answer (default 10)")
    p.set_defaults(handler=_run)
