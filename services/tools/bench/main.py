"""``nwr bench``: the reflex path of the real pipeline, measured.

Every configuration starts every service as its own process, connected
exactly as ``nwr up`` connects them (the embedded mesh of peers on loopback,
or clients of a local ``nwr router``), with the simulated skin and bridge
and the recorder running. A generated touch script touches every region in
turn, with sub-threshold touches between the reflex-causing ones. From the
recording (:mod:`nwr.services.tools.bench.core`): reflex onset, sample latency and
per-hop latencies; the lower bound (the same cores chained in this process
on the same skin samples); cost (CPU time and peak RSS per service, from
/proc, and messages lost per key from sequence gaps); the 500 Hz loops'
timing (from the Rate summaries the services log at exit). Each
configuration runs ``--reps`` times, interleaved, and the table reports the
median of each statistic over the repetitions.

The baseline (:mod:`nwr.services.tools.bench.bare`): right after each run,
the same three hops as a bare chain of zenoh-python processes with the
pipeline's Zenoh configuration, messages and rate, and no other work; every
onset figure is also given as a ratio to it, measured in the same
repetition (on a shared machine the ratios hold better than the absolute
figures), with the same chain as function calls in one process, paced at
each configuration's rate, as the floor. Where Debian's ROS 1 is installed
(rospy, rosmaster), the same chain as rospy nodes
(:mod:`nwr.services.tools.bench.ros1`) runs after each run of the embedded
mesh too, with queues of 100 and of 1: a lab's older stack in the same table.

``--cpus`` pins the bench and every process it starts to a set of CPUs:
what the pipeline does with fewer cores than the machine has.

A recorder soak test writes an hour of a busy session (a command every cycle,
state at 125 Hz) through the recorder's own decode-and-write path in this
process and samples its memory.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import BridgeSection, Profile
from nwr.services.profile import load_profile
from nwr.common.errors import ConfigError, NwrError
from nwr.common.recordings import read_recording, session_metadata
from nwr.common.robot import load_description
from nwr.services.pipeline.graph import ROUTER, Layout, process_name, recorder_args, units
from nwr.services.pipeline.supervisor import failed, spawn, stop_all, wait_for_router
from nwr.services.recorder.disk import SessionRecorder
from nwr.services.tools.bench import bare as bench_bare
from nwr.services.tools.bench import ros1 as bench_ros1
from nwr.services.tools.bench import targets as bench_targets
from nwr.services.tools.bench.bare import proc_cost
from nwr.services.tools.bench.core import (
    lower_bound,
    match_traces,
    median_over,
    source_skipped,
    summarize,
    touch_script,
)

log = logging.getLogger(__name__)

# Ports used by one run: five core services and the router; runs rotate over
# three such blocks so that a port in TIME_WAIT is never reused at once.
PORTS_PER_RUN = 6
PORT_BLOCKS = 3
BARE_S = 10.0  # how long the bare chain runs after each run (every sample is measured, not only onsets)
STARTUP_TIMEOUT_S = 60.0
SETTLE_S = 1.0  # after the script: the last reflex's first commands, the recorder's last chunk
LOOP_RE = re.compile(r"(planner|bridge): (\d+) ticks at (\d+) Hz, period p50 ([\d.]+) ms p99 ([\d.]+) ms "
                     r"worst ([\d.]+) ms, (\d+) overruns")
LIBRARIES = ("eclipse-zenoh", "msgspec", "numpy", "ruckig", "pin", "mcap")


@dataclass(frozen=True)
class Config:
    """One configuration of the pipeline."""

    name: str
    strategy: str
    rate_hz: float
    topology: str  # "embedded" (peers on loopback) or "router" (clients of a local nwr router)
    onsets: int  # reflex-causing touches of its script (0: nobody touches the arm)
    duration_s: float = 0.0  # idle configurations: how long
    state_rate_hz: float = BridgeSection().state_rate_hz


def configurations(quick: bool, onsets: int) -> list[Config]:
    if quick:
        n = 2
        return [
            Config("cartesian 25 Hz embedded", "cartesian", 25.0, "embedded", n),
            Config("cartesian 1 kHz embedded", "cartesian", 1000.0, "embedded", n, state_rate_hz=500.0),
            Config("cartesian 25 Hz router", "cartesian", 25.0, "router", n),
            Config("cartesian 1 kHz router", "cartesian", 1000.0, "router", n, state_rate_hz=500.0),
            Config("idle 25 Hz embedded", "cartesian", 25.0, "embedded", 0, duration_s=6.0),
        ]
    return [
        Config("uniform 25 Hz embedded", "uniform", 25.0, "embedded", onsets),
        Config("location 25 Hz embedded", "location", 25.0, "embedded", onsets),
        Config("cartesian 25 Hz embedded", "cartesian", 25.0, "embedded", onsets),
        Config("cartesian-smooth 25 Hz embedded", "cartesian-smooth", 25.0, "embedded", onsets),
        Config("cartesian 1 kHz embedded", "cartesian", 1000.0, "embedded", onsets, state_rate_hz=500.0),
        Config("cartesian 25 Hz router", "cartesian", 25.0, "router", onsets),
        Config("cartesian 1 kHz router", "cartesian", 1000.0, "router", onsets, state_rate_hz=500.0),
        Config("idle 25 Hz embedded", "cartesian", 25.0, "embedded", 0, duration_s=20.0),
    ]


# ------------------------------------------------------------------------------ /proc


def parse_loops(text: str) -> dict[str, dict[str, float]]:
    """The Rate summaries ("planner: N ticks at 500 Hz, period p50 ...") in a service's log."""
    out = {}
    for name, ticks, hz, p50, p99, worst, overruns in LOOP_RE.findall(text):
        out[name] = {"ticks": int(ticks), "hz": int(hz), "p50": float(p50), "p99": float(p99),
                     "worst": float(worst), "overruns": int(overruns)}
    return out


def machine() -> dict[str, Any]:
    from importlib.metadata import PackageNotFoundError, version

    model = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    libs = {}
    for lib in LIBRARIES:
        try:
            libs[lib] = version(lib)
        except PackageNotFoundError:
            libs[lib] = "-"
    return {"cpu": model, "cores": os.cpu_count(), "cpus": sorted(os.sched_getaffinity(0)),
            "python": platform.python_version(), "system": f"{platform.system()} {platform.release()}",
            "libraries": libs, "load_before": os.getloadavg()[0]}


def parse_cpus(text: str, available: set[int] | None = None) -> set[int]:
    """``--cpus``: a list of CPU numbers and ranges ("0", "0,1", "0-3,6") among those this process may use."""
    usable = os.sched_getaffinity(0) if available is None else available
    cpus: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        first, sep, last = part.partition("-")
        try:
            lo = int(first)
            hi = int(last) if sep else lo
        except ValueError:
            raise ConfigError(f"--cpus {text!r}: {part!r} is not a CPU number or a range like 0-3") from None
        if lo < 0 or hi < lo:
            raise ConfigError(f"--cpus {text!r}: {part!r} is not a CPU number or a range like 0-3")
        cpus.update(range(lo, hi + 1))
    if not cpus <= usable:
        raise ConfigError(f"--cpus {text!r}: CPU(s) {sorted(cpus - usable)} are not available to this process "
                          f"(it may use {sorted(usable)})")
    return cpus


# ------------------------------------------------------------------------------ one run


def _wait_for_line(path: Path, needle: str, procs: dict[str, subprocess.Popen[bytes]], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if needle in path.read_text(errors="replace"):
            return
        dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
        if dead:
            name = next(iter(dead))
            tail = (path.parent / f"{name}.log").read_text(errors="replace").strip().splitlines()[-5:]
            raise RuntimeError(f"service(s) exited during start-up: {dead}; the end of {name}'s log:\n  "
                               + "\n  ".join(tail))
        time.sleep(0.05)
    raise RuntimeError(f"the pipeline did not start within {timeout_s:.0f} s (no {needle!r} in {path})")


def run_once(config: Config, rep: int, base_port: int, work: Path, profile: Profile) -> dict[str, Any]:
    """One run of one configuration: start, touch, measure, stop, analyse."""
    tag = f"{re.sub(r'[^a-z0-9]+', '-', config.name.lower()).strip('-')}-{rep}"
    run_dir = work / tag
    run_dir.mkdir(parents=True, exist_ok=True)
    desc = load_description(profile.robot.description or None)
    if config.onsets:
        script, duration = touch_script(desc.pads, config.onsets, spacing_s=1.3)
    else:
        duration = config.duration_s
        script = f"# nwr bench: nobody touches the arm\nduration_s = {duration}\n"
    (run_dir / "script.toml").write_text(script)
    router_port = base_port + 5
    # The user's profile with the bench's ports, rates and output directory.
    # A copy: the profile is loaded once, so an edit of the file during the bench changes nothing.
    base = msgspec.convert(msgspec.to_builtins(profile), Profile)
    base.zenoh.base_port = base_port
    base.zenoh.router = [f"tcp/127.0.0.1:{router_port}"] if config.topology == "router" else []
    base.gateway.rate_hz = config.rate_hz
    base.bridge.state_rate_hz = config.state_rate_hz
    base.recorder.directory = str(run_dir)
    toml_path = run_dir / "profile.toml"
    toml_path.write_text(_as_toml(msgspec.to_builtins(base)))
    output = run_dir / "session.mcap"
    strategy = config.strategy
    # As `nwr up --reflex STRATEGY` starts them, from the pipeline's graph.
    layout = Layout(active=strategy, recorder=recorder_args(output, tag, strategy),
                    gateway=["--script", str(run_dir / "script.toml"), "--rate", str(config.rate_hz)],
                    router=["--listen", f"tcp/127.0.0.1:{router_port}"] if config.topology == "router" else None)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    cpu0: dict[str, float] = {}
    cpu1: dict[str, float] = {}
    rss: dict[str, float] = {}
    try:
        for unit in units(layout):
            procs[unit.label] = spawn(unit, str(toml_path), "INFO", run_dir / f"{unit.label}.log")
            if unit.service == ROUTER:
                wait_for_router(unit, procs[unit.label])
        _wait_for_line(run_dir / "gateway.log", "publishing", procs, STARTUP_TIMEOUT_S)
        t0 = time.monotonic()
        for name, proc in procs.items():
            cpu0[name] = proc_cost(proc.pid)[0]
        time.sleep(duration + SETTLE_S)
        wall = time.monotonic() - t0
        for name, proc in procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{name} exited during the run with code {proc.returncode} "
                                   f"(log: {run_dir / (name + '.log')})")
            cpu1[name], rss[name] = proc_cost(proc.pid)
    finally:
        codes = stop_all(procs)
    bad = failed(codes)
    if bad:
        raise RuntimeError(f"service(s) stopped with errors: {bad} (logs in {run_dir})")
    planner = process_name("planner", strategy)
    cpu0 = {("planner" if n == planner else n): c for n, c in cpu0.items()}
    cpu1 = {("planner" if n == planner else n): c for n, c in cpu1.items()}
    rss = {("planner" if n == planner else n): c for n, c in rss.items()}
    loops: dict[str, dict[str, float]] = {}
    for name in (planner, "bridge"):
        loops.update(parse_loops((run_dir / f"{name}.log").read_text(errors="replace")))

    records, metadata = read_recording(output)
    # Skin samples of the last 100 ms may still travel when the gateway stops.
    traces = match_traces(records, strategy, tail_ns=100_000_000)
    gaps = json.loads(metadata.get("recording", {}).get("gaps", "{}"))
    counts = json.loads(metadata.get("recording", {}).get("messages", "{}"))
    prefix = keys.prefix(base.robot.name) + "/"
    skin = [r.message for r in records if r.key == "skin/pressure"]
    lb_sample, lb_onset = lower_bound(base, strategy, skin)
    cpu = {n: cpu1[n] - cpu0[n] for n in cpu1}
    return {
        "config": config.name, "rep": rep, "rate_hz": config.rate_hz, "wall_s": wall,
        "latency_ms": {
            "onset": summarize(traces.onset),
            "sample": summarize(traces.sample),
            "gateway->gain": summarize(traces.gateway_gain),
            "gain->planner": summarize(traces.gain_planner),
            "planner->bridge": summarize(traces.planner_bridge),
            "planner->bridge: planning": summarize(traces.planner_bridge_planning),
            "planner->bridge: hop": summarize(traces.planner_bridge_hop),
            "lower bound: sample": summarize(lb_sample),
            "lower bound: onset": summarize(lb_onset),
        },
        "matching": {"skin_samples": traces.skin_samples, "unmatched_samples": traces.unmatched_samples,
                     "orphan_decisions": traces.orphan_decisions, "reflexes": traces.reflexes,
                     "onsets": len(traces.onset), "unmatched_onsets": traces.unmatched_onsets},
        "lost": {k.removeprefix(prefix): v for k, v in gaps.items()},
        "skipped_at_source": source_skipped([x.stamp_ns for x in skin], config.rate_hz),
        "messages": {k.removeprefix(prefix): v for k, v in counts.items()},
        "cpu_s": cpu,
        "cpu_percent": {n: 100.0 * c / wall for n, c in cpu.items()},
        "cpu_percent_total": 100.0 * sum(cpu.values()) / wall,
        "peak_rss_mb": rss,
        "loops": loops,
        "raw_ms": {"onset": traces.onset, "lower_bound_onset": lb_onset},
        "recording": str(output), "script_s": duration,
    }


def bare_once(config: Config, base_port: int, work: Path, seconds: float, profile: Profile) -> dict[str, float]:
    """The bare chain at ``config``'s rate and topology: latency p50/p99 (ms), samples lost, CPU %."""
    router = config.topology == "router"
    cfg = msgspec.structs.replace(profile.zenoh, base_port=base_port,
                                  router=[f"tcp/127.0.0.1:{base_port + 5}"] if router else [])
    return chain_figures(bench_bare.measure(cfg, config.rate_hz, seconds, work,
                                            router_listen=f"tcp/127.0.0.1:{base_port + 5}" if router else None))


def ros1_once(config: Config, port: int, work: Path, seconds: float, queue: int) -> dict[str, float]:
    """The same three hops in ROS 1 (:mod:`.bench_ros1`) at ``config``'s rate, queues of ``queue``: latency p50/p99
    (ms), lost, CPU %."""
    return chain_figures(bench_ros1.measure(config.rate_hz, seconds, work, port, queue))


def ros1_key(queue: int) -> str:
    """Where a run keeps the ROS 1 chain's figures with queues of ``queue``."""
    return f"ros1 q{queue}"


def chain_figures(run: bench_bare.BareRun) -> dict[str, float]:
    """A baseline chain's run as the bench reports it: latency p50/p99 (ms), samples lost, CPU %."""
    return {**bench_bare.percentiles(run.latency_ms), "lost": float(run.sent - run.received),
            "cpu_percent_total": run.cpu_percent_total}


def replay_speed(recording: Path, strategy: str, session_s: float, work: Path) -> dict[str, Any]:
    """``nwr replay --fast`` and ``nwr verify`` on a recording of the bench, each the whole command as a user runs
    it (interpreter start included): how many times real time (``session_s`` / the command's wall time), and the
    interpreter's start alone (``nwr --help``)."""
    cli = [sys.executable, "-m", "nwr.services.cli", "--log-level", "WARNING"]

    said: list[str] = []

    def timed(*argv: str, verdicts: tuple[int, ...] = (0,)) -> float:
        t = time.perf_counter()
        proc = subprocess.run([*cli, *argv], capture_output=True, text=True, timeout=600, check=False)
        if proc.returncode not in verdicts:
            raise RuntimeError(f"nwr {' '.join(argv[:2])} exited {proc.returncode}: "
                               f"{(proc.stderr or proc.stdout).strip()[-300:]}")
        said.append((proc.stdout.strip().splitlines() or [""])[-1])
        return time.perf_counter() - t

    start = timed("--help")
    replay = timed("replay", str(recording), "--fast", "--reflex", strategy, "-o", str(work / "replayed.mcap"))
    verify = timed("verify", str(recording), verdicts=(0, 1))  # 1: a run not re-made (its timing is the figure)
    return {"session_s": session_s, "replay_x": session_s / replay, "verify_x": session_s / verify,
            "start_s": start, "verify_said": said[-1]}


def _as_toml(data: dict[str, Any]) -> str:
    """A profile (plain data) as TOML: tables of scalars and lists (enough for a Profile)."""
    lines: list[str] = []

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    def table(name: str, d: dict[str, Any]) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if name:
            lines.append(f"[{name}]")
        lines.extend(f"{k} = {value(v)}" for k, v in scalars.items() if v is not None)
        lines.append("")
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{name}.{k}" if name else k, v)

    table("", data)
    return "\n".join(lines)


# ------------------------------------------------------------------------------ the recorder soak


def recorder_soak(minutes: float, path: Path, profile: Profile | None = None, *, skin_hz: float = 25.0,
                  state_hz: float = 125.0,
                  command_hz: float = 500.0, status_hz: float = 20.0) -> dict[str, Any]:
    """``minutes`` of a session written through the recorder's decode-and-write path, as fast as it goes.

    Busier than the defaults: a command every cycle (as during reflexes) and
    the state at 125 Hz.

    The messages are encoded once per kind and decoded per message with the
    key's codec, as the recorder process does, then written by a
    :class:`SessionRecorder` with the default chunking; RSS is sampled every
    simulated minute.
    """
    robot = keys.DEFAULT_ROBOT
    n = 10
    trace = m.Trace(0, 0)
    kinds = [
        (keys.SKIN_PRESSURE, skin_hz, m.SkinPressure(seq=0, stamp_ns=0, absolute_hpa=[1013.0] * n,
                                                     baseline_hpa=[1013.0] * n, change_hpa=[0.01] * n,
                                                     contact=[False] * n, valid=[True] * n)),
        (keys.SKIN_PAIN, skin_hz, m.SkinPain(seq=0, stamp_ns=0, trace=trace, model="continuous", level=[1] * n,
                                             gain=[0.0] * n)),
        (keys.planner_decision("cartesian"), skin_hz, m.PlannerDecision(seq=0, stamp_ns=0, name="cartesian",
                                                                         trace=trace, pain_seq=0, pain_stamp_ns=0)),
        (keys.robot_command("cartesian"), command_hz, m.PositionCommand(seq=0, stamp_ns=0, owner="cartesian",
                                                            q=[0.1, -1.2, 1.3, -1.6, -1.57, 0.0], trace=trace)),
        (keys.ROBOT_STATE, state_hz, m.RobotState(seq=0, stamp_ns=0, q=[0.1] * 6, dq=[0.0] * 6, status="ok",
                                                  owner="cartesian", backend="sim", stop_distance=[0.0] * 6)),
        (keys.planner_status("cartesian"), status_hz, m.PlannerStatus(seq=0, stamp_ns=0, name="cartesian",
                                                                       strategy="cartesian", mode="TASK",
                                                                       task_time_s=0.0)),
    ]
    codecs = {rel: keys.codec(rel) for rel, _, _ in kinds}
    profile = profile if profile is not None else Profile()
    streams: list[Any] = []

    def open_part(part: int) -> Any:
        stream = path.open("wb")
        streams.append(stream)
        return stream

    session = SessionRecorder(open_part, lambda _p, s: s.close(), robot, session_metadata(
        robot=robot, session="soak", profile_json="{}", strategy="cartesian", planner="cartesian",
        start_time_iso="", start_monotonic_ns=0, labels={}),
        compression=profile.recorder.compression, chunk_size=profile.recorder.chunk_size,
        chunk_interval_ns=round(profile.recorder.chunk_interval_s * 1e9))
    tick_ns = 1_000_000  # 1 ms of simulated time
    periods = [round(1e9 / hz) for _, hz, _ in kinds]
    seqs = [0] * len(kinds)
    rss: list[float] = []
    written = 0
    start = time.perf_counter()
    end_ns = round(minutes * 60e9)
    next_sample = 0
    t = 0
    while t < end_ns:
        for i, (rel, _hz, template) in enumerate(kinds):
            if t % periods[i] < tick_ns:
                payload = codecs[rel].encode(msgspec.structs.replace(template, seq=seqs[i], stamp_ns=t))
                seqs[i] += 1
                session.write(keys.key(robot, rel), codecs[rel].decode(payload), t)
                written += 1
        session.flush_if_due(t)
        if t >= next_sample:
            rss.append(_rss_mb())
            next_sample += 60_000_000_000
        t += tick_ns
    report = session.finish()
    wall = time.perf_counter() - start
    rss.append(_rss_mb())
    return {"simulated_min": minutes, "messages": written, "wall_s": wall, "speed": minutes * 60 / wall,
            "rss_mb_per_minute": rss, "rss_growth_mb": rss[-1] - rss[min(1, len(rss) - 1)],
            "lost": sum(report.gaps.values()), "file_mb": path.stat().st_size / 2**20}


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# ------------------------------------------------------------------------------ the whole bench


def aggregate(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per configuration: the median over its repetitions of every statistic."""
    out: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(r["config"] for r in runs):
        mine = [r for r in runs if r["config"] == name]
        latency = {metric: median_over([r["latency_ms"][metric] for r in mine]) for metric in mine[0]["latency_ms"]}
        services = sorted({s for r in mine for s in r["cpu_percent"]})
        loops = {loop: median_over([r["loops"][loop] for r in mine if loop in r["loops"]])
                 for loop in sorted({k for r in mine for k in r["loops"]})}
        out[name] = {
            "reps": len(mine),
            "rate_hz": mine[0]["rate_hz"],
            "latency_ms": latency,
            "ratio_to_lower_bound": {
                "sample p50": latency["sample"]["p50"] / latency["lower bound: sample"]["p50"],
                "sample p99": latency["sample"]["p99"] / latency["lower bound: sample"]["p99"],
                "onset p50": latency["onset"]["p50"] / latency["lower bound: onset"]["p50"],
                "onset p99": latency["onset"]["p99"] / latency["lower bound: onset"]["p99"],
            },
            "lost": median_over([{k: float(v) for k, v in r["lost"].items()} for r in mine]),
            "lost_total": statistics_median([sum(r["lost"].values()) for r in mine]),
            "skipped_at_source": statistics_median([r.get("skipped_at_source", float("nan")) for r in mine]),
            "cpu_percent": {s: statistics_median([r["cpu_percent"].get(s, float("nan")) for r in mine])
                            for s in services},
            "cpu_percent_total": statistics_median([r["cpu_percent_total"] for r in mine]),
            "peak_rss_mb": {s: statistics_median([r["peak_rss_mb"].get(s, float("nan")) for r in mine])
                            for s in services},
            "loops": loops,
            "matching": {k: int(sum(r["matching"][k] for r in mine)) for k in mine[0]["matching"]},
        }
        for key in map(ros1_key, bench_ros1.QUEUE_SIZES):
            ros1 = [r[key] for r in mine if r.get(key)]
            if ros1:
                out[name][key] = median_over(ros1)
        bare = [r["bare"] for r in mine if r.get("bare")]
        if bare:
            out[name]["bare"] = median_over(bare)
            # The ratio per repetition (pipeline and chain measured back to back), then the median.
            out[name]["ratio_to_bare"] = {
                q: statistics_median([r["latency_ms"]["onset"][q] / r["bare"][q] for r in mine if r.get("bare")])
                for q in ("p50", "p99")}
    return out


def baseline_table(summary: dict[str, dict[str, Any]],
                   floors: dict[str, dict[str, float]]) -> tuple[list[str], list[list[str]]]:
    """Reflex onset against the bare chain of the same rate and topology (the ratios: the headline); ``floors``:
    the in-process chain's figures per rate (:func:`in_process_floors`)."""
    header = ["configuration", "onset p50", "bare p50", "x bare", "onset p99", "bare p99", "x bare",
              "bare lost", "in-process p50"]
    queues = [q for q in bench_ros1.QUEUE_SIZES if any(s.get(ros1_key(q)) for s in summary.values())]
    for q in queues:
        header += [f"ROS 1 q{q} p50", "p99", "lost"]
    rows = []
    for name, s in summary.items():
        bare = s.get("bare")
        if not bare:
            continue
        onset = s["latency_ms"]["onset"]
        row = [name, _f(onset["p50"], ".3f"), _f(bare["p50"], ".3f"), _f(s["ratio_to_bare"]["p50"], ".2f"),
               _f(onset["p99"], ".3f"), _f(bare["p99"], ".3f"), _f(s["ratio_to_bare"]["p99"], ".2f"),
               _f(bare["lost"], ".0f"), _f(floors.get(f"{s['rate_hz']:g}", {}).get("p50", float("nan")), ".4f")]
        for q in queues:
            ros1 = s.get(ros1_key(q))
            row += [_f(ros1["p50"], ".3f"), _f(ros1["p99"], ".3f"), _f(ros1["lost"], ".0f")] if ros1 else ["-"] * 3
        rows.append(row)
    return header, rows


def statistics_median(values: list[float]) -> float:
    finite = [v for v in values if not np.isnan(v)]
    return float(np.median(finite)) if finite else float("nan")


def _f(x: float, fmt: str = ".2f") -> str:
    return "-" if x is None or np.isnan(x) else format(x, fmt)


def tables(summary: dict[str, dict[str, Any]]) -> tuple[list[str], list[list[str]], list[str], list[list[str]]]:
    """The latency table and the cost/loop table."""
    header = ["configuration", "latency (ms)", "n", "p50", "p90", "p99", "max", "lost", "skipped", "CPU %"]
    rows: list[list[str]] = []
    for name, s in summary.items():
        first = True
        for metric, st in s["latency_ms"].items():
            if st["n"] == 0 or np.isnan(st["n"]):
                continue
            rows.append([name if first else "", metric, str(int(st["n"])), _f(st["p50"], ".3f"), _f(st["p90"], ".3f"),
                         _f(st["p99"], ".3f"), _f(st["max"], ".3f"),
                         _f(s["lost_total"], ".0f") if first else "",
                         _f(s.get("skipped_at_source", float("nan")), ".0f") if first else "",
                         _f(s["cpu_percent_total"], ".1f") if first else ""])
            first = False
    cost_header = ["configuration", "service", "CPU % of a core", "peak RSS (MB)", "loop p50 (ms)", "loop p99 (ms)",
                   "loop worst (ms)", "overruns"]
    cost: list[list[str]] = []
    for name, s in summary.items():
        for i, service in enumerate(s["cpu_percent"]):
            loop = s["loops"].get(service, {})
            cost.append([name if i == 0 else "", service, _f(s["cpu_percent"][service], ".1f"),
                         _f(s["peak_rss_mb"][service], ".0f"), _f(loop.get("p50", float("nan")), ".3f"),
                         _f(loop.get("p99", float("nan")), ".3f"), _f(loop.get("worst", float("nan")), ".2f"),
                         _f(loop.get("overruns", float("nan")), ".0f")])
    return header, rows, cost_header, cost


def text_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    out = ["  ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(zip(header, widths)))]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
    return "\n".join(out)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |",
           "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def report_markdown(result: dict[str, Any]) -> str:
    mach = result["machine"]
    header, rows, cost_header, cost = tables(result["summary"])
    libs = ", ".join(f"{k} {v}" for k, v in mach["libraries"].items())
    lines = [
        f"# nwr bench, {result['started']}",
        "",
        f"Machine: {mach['cpu']}, {mach['cores']} cores, {mach['system']}; Python {mach['python']}; {libs}. "
        f"Load average before the run: {mach['load_before']:.2f}."
        + (f" Every process of the bench pinned to CPU(s) {', '.join(map(str, mach['cpus']))} (`--cpus`)."
           if mach.get("pinned") else ""),
        "",
        f"{result['reps']} repetition(s) of each configuration, interleaved; every figure is the median over them. "
        "Latencies in ms on the machine's monotonic clock; *lost*: messages missing from the recording (sequence "
        "gaps, all keys); *skipped*: skin sample periods the simulated skin's loop, late, let pass without a "
        "sample (no sequence gap: never taken); *CPU %*: all services together, % of one core, from the script's "
        "start to its end.",
        "",
        markdown_table(header, rows),
        "",
    ]
    base_header, base_rows = baseline_table(result["summary"], result.get("in_process_ms", {}))
    if base_rows:
        lines += [
            "Reflex onset against the baseline: the same three hops as a bare chain of zenoh-python processes "
            "(the pipeline's Zenoh configuration, messages and rate; no other work), run right after each "
            "repetition; *x bare*: the ratio per repetition, median; *in-process*: the chain as function calls in "
            "one process, paced at the configuration's rate"
            + ("; *ROS 1 qN*: the same chain as rospy nodes with their own rosmaster (Debian's ROS 1), peers only, "
               "decoding and building the same numbers as float arrays, publishers' and subscribers' queues of N "
               "(*lost*: samples a queue of 1 dropped)."
               if any(k.startswith("ros1") for s in result["summary"].values() for k in s) else "."),
            "",
            markdown_table(base_header, base_rows),
            "",
        ]
    lines += [
        "Cost per service (CPU % of one core over the run, peak RSS) and the 500 Hz loops' timing (Rate summary "
        "over the last 4096 cycles):",
        "",
        markdown_table(cost_header, cost),
        "",
    ]
    target_header, target_rows = bench_targets.verdict_rows({"this run": result})
    lines += ["The targets (`nwr.services.tools.bench.targets`: each judged on this run's figures):", "",
              markdown_table(target_header, target_rows), ""]
    for failure in result.get("failures", []):
        lines += [f"Failed: {failure['config']}, repetition {failure['rep'] + 1}: {failure['error']}", ""]
    soak = result.get("recorder_soak")
    if soak:
        lines += [
            f"Recorder soak: {soak['simulated_min']:g} simulated minutes ({soak['messages']} messages: a command every "
            f"cycle, state at 125 Hz) through the recorder's decode-and-write path in {soak['wall_s']:.0f} s; RSS "
            f"{soak['rss_mb_per_minute'][1 if len(soak['rss_mb_per_minute']) > 1 else 0]:.1f} MB after the first "
            f"minute, {soak['rss_mb_per_minute'][-1]:.1f} MB at the end (growth {soak['rss_growth_mb']:+.1f} MB); "
            f"{soak['lost']} lost; file {soak['file_mb']:.1f} MB.",
            "",
        ]
    return "\n".join(lines)


def run_bench(args: argparse.Namespace) -> dict[str, Any]:
    onsets = args.onsets
    configs = configurations(args.quick, onsets)
    if args.only:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        configs = [c for c in configs if any(w in c.name for w in wanted)]
        if not configs:
            raise ConfigError(f"--only {args.only!r} matches no configuration; they are "
                              f"{[c.name for c in configurations(args.quick, onsets)]}")
    reps = args.reps if args.reps else (1 if args.quick else 3)
    profile = load_profile(args.profile)
    if args.cpus:
        # Inherited by every process the bench starts: the services, the router, the bare chain.
        os.sched_setaffinity(0, parse_cpus(args.cpus))
    started = dt.datetime.now()
    out_dir = Path(args.output) if args.output else Path("bench") / started.strftime("%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="nwr-bench-", dir=out_dir if args.keep else None))
    result: dict[str, Any] = {"started": started.isoformat(timespec="seconds"), "quick": args.quick, "reps": reps,
                              "machine": {**machine(), "pinned": bool(args.cpus)}, "runs": [], "failures": []}
    # The optional ROS 1 chain: where Debian's rospy and rosmaster are installed, unless --no-ros1.
    ros1: str | None = "--no-ros1" if args.no_ros1 else bench_ros1.available()
    result["ros1"] = {"ran": ros1 is None, "why_not": ros1}
    if ros1 is not None:
        print(f"the ROS 1 chain does not run: {ros1}", flush=True)
    total = reps * len(configs)
    done = 0
    t_start = time.monotonic()
    try:
        for rep in range(reps):
            for config in configs:
                port = args.base_port + (done % PORT_BLOCKS) * PORTS_PER_RUN
                print(f"[{done + 1}/{total}] {config.name}, repetition {rep + 1} (ports {port}-{port + 5}) ...",
                      end="", flush=True)
                t = time.monotonic()
                done += 1
                try:
                    run = run_once(config, rep, port, work, profile)
                except (RuntimeError, OSError, NwrError) as exc:
                    # One failed run (a port taken by someone else, say) must not lose the others.
                    print(f" failed: {exc}", flush=True)
                    result["failures"].append({"config": config.name, "rep": rep, "error": str(exc)})
                    continue
                result["runs"].append(run)
                if "replay" not in result and config.rate_hz == 25.0 and config.onsets and config.strategy == \
                        "cartesian" and config.topology == "embedded":
                    try:
                        result["replay"] = replay_speed(Path(run["recording"]), config.strategy, run["script_s"],
                                                        work)
                    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
                        result["replay"] = {"error": f"timing the replay failed: {exc}"}
                lat = run["latency_ms"]
                print(f" {time.monotonic() - t:.0f} s: onset p99 {_f(lat['onset']['p99'])} ms "
                      f"({lat['onset']['n']}), sample p99 {_f(lat['sample']['p99'])} ms ({lat['sample']['n']}), "
                      f"CPU {run['cpu_percent_total']:.0f} %", flush=True)
                if config.onsets:
                    bare_port = args.base_port + (PORT_BLOCKS + done % PORT_BLOCKS) * PORTS_PER_RUN
                    bare = _baseline(result, run, rep, config, "bare", "bare chain", partial(
                        bare_once, config, bare_port, work / f"bare-{done}", args.bare_seconds, profile))
                    if bare is not None:
                        print(f"; onset p50 {lat['onset']['p50'] / bare['p50']:.2f}x the chain's", end="")
                    print(flush=True)
                if config.onsets and ros1 is None and config.topology == "embedded":
                    for i, queue in enumerate(bench_ros1.QUEUE_SIZES):
                        ros_port = args.base_port + (2 * PORTS_PER_RUN + i) * PORT_BLOCKS + done % PORT_BLOCKS
                        _baseline(result, run, rep, config, ros1_key(queue), f"ROS 1 chain, queues of {queue}",
                                  partial(ros1_once, config, ros_port, work / f"ros1-q{queue}-{done}",
                                          args.bare_seconds, queue))
                        print(flush=True)
        if args.soak_minutes > 0:
            print(f"recorder soak: {args.soak_minutes:g} simulated minutes ...", end="", flush=True)
            result["recorder_soak"] = recorder_soak(args.soak_minutes, work / "soak.mcap", profile)
            soak = result["recorder_soak"]
            print(f" {soak['wall_s']:.0f} s, RSS growth {soak['rss_growth_mb']:+.1f} MB", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    result["summary"] = aggregate(result["runs"])
    result["in_process_ms"] = in_process_floors(configs, args.bare_seconds)
    result["elapsed_s"] = time.monotonic() - t_start
    (out_dir / "bench.json").write_text(json.dumps(result, indent=1, default=_jsonable))
    md = report_markdown(result)
    (out_dir / "bench.md").write_text(md)
    header, rows, cost_header, cost = tables(result["summary"])
    base_header, base_rows = baseline_table(result["summary"], result["in_process_ms"])
    if base_rows:
        print("\nreflex onset against the bare zenoh chain of the same rate and topology (ms; x: ratio, per "
              "repetition, median):")
        print(text_table(base_header, base_rows))
    print()
    print(text_table(header, rows))
    print()
    print(text_table(cost_header, cost))
    print()
    print(text_table(*bench_targets.verdict_rows({"this run": result})))
    print(f"\nraw numbers: {out_dir / 'bench.json'}; table: {out_dir / 'bench.md'} ({result['elapsed_s']:.0f} s)")
    result["output"] = str(out_dir)
    return result


def in_process_floors(configs: list[Config], seconds: float) -> dict[str, dict[str, float]]:
    """The chain as function calls in this process, paced at each touched configuration's rate for ``seconds``
    (as long as the bare chain runs): its p50 and p99 per rate, ms, keyed ``f"{rate:g}"``."""
    rates = sorted({c.rate_hz for c in configs if c.onsets})
    return {f"{r:g}": bench_bare.percentiles(bench_bare.in_process(max(1, round(seconds * r)), r)) for r in rates}


def _baseline(result: dict[str, Any], run: dict[str, Any], rep: int, config: Config, key: str, label: str,
              measure: Callable[[], dict[str, float]]) -> dict[str, float] | None:
    """A chain measured after a run (``run[key]``), its figures printed on a line left open; a failure is noted in
    ``result`` and loses nothing else."""
    try:
        figures = run[key] = measure()
    except (RuntimeError, OSError, ValueError, NwrError) as exc:
        print(f"  the {label} failed: {exc}", end="")
        result["failures"].append({"config": f"{label}: {config.name}", "rep": rep, "error": str(exc)})
        return None
    print(f"  {label}: p50 {_f(figures['p50'], '.3f')} ms, p99 {_f(figures['p99'], '.3f')} ms, "
          f"{figures['lost']:.0f} lost", end="")
    return figures


def _jsonable(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if hasattr(x, "__dataclass_fields__"):
        return asdict(x)
    return str(x)


def _handler(args: argparse.Namespace) -> int:
    if args.also_unpinned and not args.cpus:
        raise ConfigError("--also-unpinned goes with --cpus: the pinned run first, then the same unpinned")
    everything = os.sched_getaffinity(0)
    base = Path(args.output) if args.output else Path("bench") / dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    pinned = argparse.Namespace(**{**vars(args), "output": str(base / "pinned")}) if args.also_unpinned else args
    results = {f"pinned to CPU(s) {args.cpus}" if args.cpus else "this run": run_bench(pinned)}
    if args.also_unpinned:
        os.sched_setaffinity(0, everything)
        unpinned = argparse.Namespace(**{**vars(args), "cpus": None, "output": str(base / "unpinned")})
        print(f"\nthe same bench, unpinned (CPUs {sorted(everything)}):", flush=True)
        results[f"unpinned ({len(everything)} CPUs)"] = run_bench(unpinned)
        header, rows = bench_targets.verdict_rows(results)
        print("\nthe targets, pinned and unpinned side by side:")
        print(text_table(header, rows))
        both = base / "targets.md"
        both.write_text("# nwr bench: the targets, pinned and unpinned\n\n" + markdown_table(header, rows) + "\n")
        print(f"\nside by side: {both}")
    for result in results.values():
        unmatched = sum(s["matching"]["unmatched_samples"] for s in result["summary"].values())
        if unmatched:
            log.warning("%d skin samples had no decision of the active planner", unmatched)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="measure the reflex path of the real pipeline (latency, lower bound, cost, loop timing)",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--quick", action="store_true", help="a smoke run: one repetition, short scripts (81-132 s on a loaded 2-core machine)")
    p.add_argument("--reps", type=int, default=0, help="repetitions of each configuration (default 3; --quick 1)")
    p.add_argument("--onsets", type=int, default=30, help="reflex-causing touches per run (default 30)")
    p.add_argument("--only", metavar="NAMES", help="comma-separated substrings of the configurations to run")
    p.add_argument("--soak-minutes", type=float, default=None,
                   help="simulated minutes of the recorder soak (default 60; --quick 0.5; 0 = none)")
    p.add_argument("--base-port", type=int, default=18050,
                   help=f"first of the {(2 * PORTS_PER_RUN + len(bench_ros1.QUEUE_SIZES)) * PORT_BLOCKS} loopback "
                        "ports the runs, the bare chain and the ROS 1 chains' rosmasters use (default 18050)")
    p.add_argument("--bare-seconds", type=float, default=BARE_S,
                   help=f"how long the bare chain runs after each run (default {BARE_S:g}; --quick 3)")
    p.add_argument("--no-ros1", action="store_true",
                   help="skip the ROS 1 chain (by default it runs after each embedded run where Debian's rospy "
                        "and rosmaster are installed)")
    p.add_argument("--cpus", metavar="LIST",
                   help="pin the bench and every process it starts to these CPUs (e.g. 0 or 0-1,4): what the "
                        "pipeline does with fewer cores than the machine has")
    p.add_argument("--also-unpinned", action="store_true",
                   help="with --cpus: the bench pinned into <output>/pinned, then the whole bench again unpinned "
                        "into <output>/unpinned, and the targets of both side by side in <output>/targets.md; "
                        "`make bench` does this")
    p.add_argument("--output", "-o", help="directory for bench.json and bench.md (default: bench/<time>/)")
    p.add_argument("--keep", action="store_true", help="keep every run's recording, logs and profile")
    p.add_argument("--tracking", action="store_true",
                   help="instead: how the bridge's tracker follows the planner (jerk, acceleration, tracking error, "
                        "the task's fastest point, reflex onsets, stops, cost per cycle), in this process on "
                        "simulated time (a minute)")
    p.add_argument("--strategies", action="store_true",
                   help="instead: what each reflex strategy costs the planner per control cycle (every pad at "
                        "three gains from three poses, in this process; medians as ratios to the Cartesian "
                        "reflex's)")
    p.add_argument("--against", metavar="TRACKING_PY",
                   help="with --tracking: compare with another version of services/bridge/tracking.py, "
                        "e.g. git show REV:services/bridge/tracking.py > old.py (a revision after its split "
                        "into reference, law, limits and stop: only tracking.py itself is the other version's)")
    p.add_argument("--jitter-ms", type=float, default=0.0,
                   help="with --tracking: delay each command by up to this much, each bridge cycle by a quarter "
                        "of it (seeded), as a loaded machine does")
    p.set_defaults(handler=_handler_with_defaults)


def _in_process(args: argparse.Namespace, name: str,
                run: Callable[[Profile, Callable[[dict[str, Any]], None]], list[dict[str, Any]]]) -> int:
    """An in-process measurement: ``run`` prints one row per line as it goes; ``--output``: ``<name>.json``."""
    profile = load_profile(args.profile)

    def show(row: dict[str, Any]) -> None:
        print(", ".join(f"{k} {_f(v, '.4g') if isinstance(v, float) else v}" for k, v in row.items()), flush=True)

    rows = run(profile, show)
    if args.output:
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{name}.json").write_text(json.dumps(rows, indent=1, default=_jsonable))
        print(f"raw numbers: {out / f'{name}.json'}")
    return 0


def run_tracking(args: argparse.Namespace) -> int:
    """``nwr bench --tracking``: the tracker's figures (:mod:`.bench_tracking`), one row per session and version."""
    from nwr.services.tools.bench import tracking as bench_tracking

    return _in_process(args, "tracking", lambda profile, show: bench_tracking.run(
        profile, against=args.against, jitter_ms=args.jitter_ms, print_row=show))


def run_strategies(args: argparse.Namespace) -> int:
    """``nwr bench --strategies``: each strategy's cost per planner cycle (:mod:`.bench_strategies`)."""
    from nwr.services.tools.bench import strategies as bench_strategies

    return _in_process(args, "strategies", lambda profile, show: bench_strategies.run(profile, print_row=show))


def _handler_with_defaults(args: argparse.Namespace) -> int:
    if args.tracking:
        return run_tracking(args)
    if args.strategies:
        return run_strategies(args)
    if args.soak_minutes is None:
        args.soak_minutes = 0.5 if args.quick else 60.0
    if args.quick:
        args.bare_seconds = min(args.bare_seconds, 3.0)
    if args.reps < 0 or args.onsets < 1:
        raise ConfigError(f"--reps ({args.reps}) must be >= 0 and --onsets ({args.onsets}) >= 1")
    return _handler(args)
