"""Does the physics world run the demo in real time beside the services? Worlds and skins, alternated.

    .venv/bin/python scripts/benchmarks/world_real_time.py [--runs 3] [--script demo] [--keep DIR]
        [--worlds scripted,physics] [--base-port PORT]

Each run is one live ``nwr demo --world W`` (every service its own
process, the bridge at 500 Hz; ``default``: no ``--world``, the demo's
default); ``W+taxels`` runs it on the taxel skin (``--skin taxels``) at
1 kHz: the physics world's ``bridge.physics.taxel_rate_hz``, or in the
scripted world ``gateway.rate_hz = 1000``. The configurations are
alternated run by run (ABBA order: forward, then backward, so a drift in
the machine's load falls on all). Each run has a profile of its own on
fresh ports (``--base-port``, or a random free range), so that it never
meets another pipeline on the machine. Per run:

- CPU per service (user + system, s, over the session): read from
  ``/proc/<pid>/stat`` of the demo's children every 0.2 s (the last reading
  before each exits; Linux only);
- the bridge's and the planner's loops: p99 and worst period (ms) and
  overruns, from the lines they log when they stop;
- world time lost (physics only, s): how far the world's own clock fell
  behind the bridge's over the session, from the recording's ``world/skin``
  (its bridge stamps against its world times);
- the median reflex onset latency (ms) and whether the script's touches
  came out as expected, from the demo's summary;
- the load average (1 min) at the start and end of the run.

It prints each run and the medians per world. The machine is shared: read
the figures beside the load.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from nwr.common import keys
from nwr.common.recordings import read_recording

NWR = str(Path(sys.executable).with_name("nwr"))
WORLDS = ("scripted", "physics", "default")
TAXEL_RATE_HZ = 1000.0  # the scripted taxel skin's gateway.rate_hz, as the physics world's taxel_rate_hz
TICK = os.sysconf("SC_CLK_TCK")
LOOP = re.compile(r"(\w+): \d+ ticks at \d+ Hz, period p50 [\d.]+ ms p99 ([\d.]+) ms worst ([\d.]+) ms, (\d+) overruns")
STARTED = re.compile(r"(\S+) \(pid (\d+)\)")
ONSET = re.compile(r"reflex onset latency over \d+ reflexes: median ([\d.]+) ms")


@dataclass
class Run:
    world: str
    load: tuple[float, float] = (0.0, 0.0)
    cpu_s: dict[str, float] = field(default_factory=dict)
    loops: dict[str, tuple[float, float, int]] = field(default_factory=dict)  # p99 ms, worst ms, overruns
    lost_s: float | None = None
    skin_hz: float | None = None
    onset_ms: float | None = None
    as_expected: bool = False
    failed: str = ""  # the demo's last lines when it did not run its session through (the run is left out)


def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` now."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            parents.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def cpu_of(pid: int) -> float | None:
    """A process's user + system CPU time so far, s (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / TICK


def world_lost_s(path: Path) -> float | None:
    """How far the physics world's clock fell behind the bridge's over the recording, s (None: no world)."""
    records, _ = read_recording(path, only=lambda key: key == keys.WORLD_SKIN)
    if len(records) < 2:
        return None
    first, last = records[0].message, records[-1].message
    return ((last.stamp_ns - first.stamp_ns) - (last.world_ns - first.world_ns)) / 1e9


def skin_hz(path: Path) -> float | None:
    """The gateway's skin samples per second over the recording (what reached the pipeline of the rate asked)."""
    records, _ = read_recording(path, only=lambda key: key == keys.SKIN_PRESSURE)
    if len(records) < 2:
        return None
    return (len(records) - 1) / ((records[-1].message.stamp_ns - records[0].message.stamp_ns) / 1e9)


def free_base_port(count: int = 5) -> int:
    """A random base port whose ``count`` ports are free on loopback now."""
    rng = random.Random()
    while True:
        base = rng.randrange(20000, 60000 - count)
        try:
            for port in range(base, base + count):
                with socket.socket() as probe:
                    probe.bind(("127.0.0.1", port))
        except OSError:
            continue
        return base


def profile_for(config: str, base_port: int | None, out: Path) -> Path:
    """The run's profile: its own ports; a scripted taxel skin at 1 kHz."""
    world, _, skin = config.partition("+")
    text = f"[zenoh]\nbase_port = {base_port if base_port else free_base_port()}\n"
    if skin == "taxels" and world == "scripted":
        text += f"\n[gateway]\nrate_hz = {TAXEL_RATE_HZ}\n"
    path = out / f"profile-{time.monotonic_ns()}.toml"
    path.write_text(text)
    return path


def run(config: str, script: str, out: Path, base_port: int | None = None) -> Run:
    result = Run(config, load=(os.getloadavg()[0], 0.0))
    world, _, skin = config.partition("+")
    path = out / f"{world}-{skin or 'pads'}-{time.monotonic_ns()}.mcap"
    command = [NWR, "--profile", str(profile_for(config, base_port, out)), "demo", "--script", script,
               *(("--world", world) if world != "default" else ()), *(("--skin", skin) if skin else ()),
               "-o", str(path), "--stop-on-exit"]
    seen: dict[int, float] = {}
    with tempfile.TemporaryFile("w+") as log:
        demo = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True)
        try:
            while demo.poll() is None:
                for pid in children(demo.pid):
                    cpu = cpu_of(pid)
                    if cpu is not None:
                        seen[pid] = cpu
                time.sleep(0.2)
        finally:
            if demo.poll() is None:
                demo.terminate()
                demo.wait(30)
        log.seek(0)
        text = log.read()
    result.load = (result.load[0], os.getloadavg()[0])
    names = {}
    for line in text.splitlines():
        if "started " in line:
            names.update({int(pid): name for name, pid in STARTED.findall(line)})
        loop = LOOP.search(line)
        if loop:
            result.loops[loop.group(1)] = (float(loop.group(2)), float(loop.group(3)), int(loop.group(4)))
        onset = ONSET.search(line)
        if onset:
            result.onset_ms = float(onset.group(1))
    result.as_expected = "as expected" in text
    result.cpu_s = {name: seen.get(pid, 0.0) for pid, name in names.items()}
    if "bridge" not in result.loops:
        result.failed = f"nwr demo exited {demo.returncode}:\n{text[-2000:]}"
    if path.exists():
        result.lost_s = world_lost_s(path)
        result.skin_hz = skin_hz(path)
    return result


def row(r: Run) -> str:
    if r.failed:
        return f"{r.world:>15}  load {r.load[0]:4.1f}-{r.load[1]:4.1f}  FAILED (left out): {r.failed}"
    bridge = r.loops.get("bridge", (float("nan"), float("nan"), -1))
    planner = r.loops.get("planner", (float("nan"), float("nan"), -1))
    total = sum(r.cpu_s.values())
    lost = "-" if r.lost_s is None else f"{r.lost_s:.3f}"
    onset = "-" if r.onset_ms is None else f"{r.onset_ms:.2f}"
    return (f"{r.world:>15}  load {r.load[0]:4.1f}-{r.load[1]:4.1f}  bridge CPU {r.cpu_s.get('bridge', 0.0):5.2f} s  "
            f"all {total:5.2f} s  bridge p99/worst {bridge[0]:.2f}/{bridge[1]:.1f} ms, {bridge[2]} overruns  "
            f"planner {planner[2]} overruns  lost {lost} s  skin {r.skin_hz or 0.0:.0f}/s  onset p50 {onset} ms  "
            f"{'as expected' if r.as_expected else 'NOT as expected'}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--runs", type=int, default=3, help="runs per world (default 3)")
    parser.add_argument("--script", default="demo", help="touch script (default: demo)")
    parser.add_argument("--keep", type=Path, help="keep the recordings here (default: a temporary directory)")
    parser.add_argument("--worlds", default="scripted,physics",
                        help="the configurations to alternate (two or more), each a world (scripted, physics or "
                             "default: no --world, the demo's default), +taxels for the taxel skin at 1 kHz; "
                             "default: scripted,physics")
    parser.add_argument("--base-port", type=int,
                        help="the demo's zenoh.base_port (it uses five ports from it; default: a random free range "
                             "per run)")
    args = parser.parse_args()
    worlds = tuple(args.worlds.split(","))
    bad = [w for w in worlds if w.partition("+")[0] not in WORLDS or w.partition("+")[2] not in ("", "taxels")]
    if len(worlds) < 2 or len(set(worlds)) != len(worlds) or bad:
        parser.error(f"--worlds {args.worlds}: two or more different configurations, each one of {', '.join(WORLDS)}, "
                     "optionally +taxels")
    runs: list[Run] = []
    with tempfile.TemporaryDirectory() as scratch:
        out = args.keep or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        for i in range(args.runs):
            order = worlds if i % 2 == 0 else worlds[::-1]
            for world in order:
                runs.append(run(world, args.script, out, args.base_port))
                print(row(runs[-1]), flush=True)
    print("\nmedians per configuration (x: against the first's):")
    baseline = [sum(r.cpu_s.values()) for r in runs if r.world == worlds[0] and not r.failed]
    base_all = statistics.median(baseline) if baseline else float("nan")
    for world in worlds:
        mine = [r for r in runs if r.world == world and not r.failed]
        if not mine:
            print(f"  {world}: no run went through")
            continue
        services = sorted({s for r in mine for s in r.cpu_s})
        cpu = ", ".join(f"{s} {statistics.median(r.cpu_s.get(s, 0.0) for r in mine):.2f}" for s in services)
        bridge = [r.loops["bridge"] for r in mine if "bridge" in r.loops]
        lost = [r.lost_s for r in mine if r.lost_s is not None]
        onset = [r.onset_ms for r in mine if r.onset_ms is not None]
        total = statistics.median(sum(r.cpu_s.values()) for r in mine)
        rates = [r.skin_hz for r in mine if r.skin_hz is not None]
        print(f"  {world}: CPU s {cpu}; all {total:.2f} (x{total / base_all:.2f}); skin samples "
              f"{statistics.median(rates) if rates else float('nan'):.0f}/s")
        if bridge:
            print(f"    bridge p99 {statistics.median(b[0] for b in bridge):.2f} ms, worst "
                  f"{statistics.median(b[1] for b in bridge):.1f} ms, overruns "
                  f"{statistics.median(b[2] for b in bridge):.0f}; onset p50 "
                  f"{statistics.median(onset) if onset else float('nan'):.2f} ms; world time lost "
                  f"{f'{statistics.median(lost):.3f} s' if lost else '- (no world)'}; as expected "
                  f"{sum(r.as_expected for r in mine)}/{len(mine)}; load {min(r.load[0] for r in mine):.1f}-"
                  f"{max(r.load[1] for r in mine):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
