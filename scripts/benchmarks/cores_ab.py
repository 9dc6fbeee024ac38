"""CPU time of each service's re-run of a recording (``nwr verify``'s), previous code against this, in one process.

    git archive REV common services | (mkdir -p /tmp/before/nwr && tar -x -C /tmp/before/nwr)
    .venv/bin/python scripts/benchmarks/cores_ab.py REC.mcap --before /tmp/before \\
        --patch services/bridge/limits.py:JointLimits.guard --patch services/bridge/core.py:BridgeCore._setpoint

Each ``--patch FILE:CLASS.ATTR`` (or ``FILE:FUNCTION``) is loaded from the
``--before`` tree and set in place of this tree's for the A runs; the B runs
use this tree's. A and B alternate ``--pairs`` times in this process (the same
warm-up, the same imports); every run must re-make the recorded outputs bit
for bit. Prints each service's CPU seconds (``time.process_time``), their
medians, the ratio B/A and the machine's load: on a shared machine the ratio
holds better than the seconds. With ``--onsets`` it also prints the
planner's time on each pain message that starts a reflex (the work before its
first command) and on the others.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import statistics
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

from nwr.services.planner import core as planner_core
from nwr.services.tools.recordings import verify


def _load(tree: Path, file: str) -> ModuleType:
    """The module at ``tree``/nwr/``file`` under a name of its own (its imports are this tree's)."""
    name = "before_" + file.removesuffix(".py").replace("/", "_")
    spec = importlib.util.spec_from_file_location(name, tree / "nwr" / file)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _target(file: str, path: str) -> tuple[Any, str]:
    """The object holding ``path``'s last name in this tree's module of ``file``, and that name."""
    dotted = "nwr." + file.removesuffix(".py").replace("/", ".")
    module = importlib.import_module(dotted)
    *owners, attr = path.split(".")
    holder: Any = module
    for owner in owners:
        holder = getattr(holder, owner)
    return holder, attr


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording")
    parser.add_argument("--before", type=Path, required=True, help="a tree holding nwr/common and nwr/services")
    parser.add_argument("--patch", action="append", default=[], metavar="FILE:NAME",
                        help="a function or method to take from --before (FILE relative to the repository)")
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--onsets", action="store_true", help="also time the planner's work on each pain message")
    args = parser.parse_args()

    patches = []
    for spec in args.patch:
        file, name = spec.split(":")
        holder, attr = _target(file, name)
        old: Any = _load(args.before, file)
        for part in name.split(".")[:-1]:
            old = getattr(old, part)
        patches.append((holder, attr, getattr(old, attr), holder.__dict__[attr]))

    cpu: dict[str, dict[str, list[float]]] = {"A": {}, "B": {}}
    run_verify = verify.verify_run

    def timed(run: Any, *a: Any, **k: Any) -> Any:
        t = time.process_time()
        result = run_verify(run, *a, **k)
        cpu[side].setdefault(run.service, []).append(time.process_time() - t)
        return result

    verify.verify_run = timed  # type: ignore[assignment]
    onsets: list[float] = []
    others: list[float] = []
    on_pain = planner_core.Planner.on_pain

    def timed_pain(self: Any, pain: Any, now_ns: int) -> Any:
        t = time.perf_counter_ns()
        command = on_pain(self, pain, now_ns)
        (onsets if command is not None else others).append((time.perf_counter_ns() - t) / 1e3)
        return command

    if args.onsets:
        planner_core.Planner.on_pain = timed_pain  # type: ignore[method-assign]
    loads = [os.getloadavg()[0]]
    for _ in range(args.pairs):
        for side in ("A", "B"):
            for holder, attr, old_fn, new_fn in patches:
                setattr(holder, attr, old_fn if side == "A" else new_fn)
            with contextlib.redirect_stdout(io.StringIO()):
                results = verify.verify(args.recording)
            bad = [r.format() for r in results if r.verdict != "identical"]
            if bad:
                print(f"{side}: not bit for bit:", *bad, sep="\n  ")
                return 1
        loads.append(os.getloadavg()[0])
    print(f"{args.pairs} pairs alternated, load {min(loads):.2f}-{max(loads):.2f}; CPU s, median (runs)")
    for service in cpu["A"]:
        a, b = cpu["A"][service], cpu["B"][service]
        ratio = statistics.median(b) / statistics.median(a) if statistics.median(a) else float("nan")
        print(f"{service:<20s} A {statistics.median(a):7.3f}  B {statistics.median(b):7.3f}  B/A {ratio:.3f}  "
              f"(A {[round(x, 3) for x in a]}, B {[round(x, 3) for x in b]})")
    if args.onsets and onsets:
        for label, xs in (("starts a reflex", onsets), ("starts none", others)):
            xs = sorted(xs)
            print(f"planner on_pain that {label}: n {len(xs)}, p50 {xs[len(xs) // 2]:.1f} us, "
                  f"p90 {xs[int(len(xs) * 0.9)]:.1f} us, max {xs[-1]:.1f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
