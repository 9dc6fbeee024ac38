"""``nwr summary``: the per-touch table of a recording, and whether it matches its touch script."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from nwr.common.config import Profile, load_profile
from nwr.common.launch import load_script, profile_for


def print_summary(path: Path, script_name: str | None, profile: Profile | None = None, *, wide: bool = False,
                  columns: str | None = None) -> int:
    """Print the per-touch table of the recording ``path`` (the essential columns, or every one: ``wide``, or
    ``columns``: names, comma-separated) and write every column to ``<recording>.touches.csv``."""
    from nwr.common.recordings import read_recording
    from nwr.common.robot import load_description
    from nwr.services.tools.recordings import analysis, table

    chosen = table.columns(wide, columns)  # an unknown column is refused before the recording is read
    width = table.width(wide)

    records, metadata = read_recording(path)
    profile = profile or load_profile(None)
    desc = load_description(profile.robot.description or None)
    touches = analysis.summarize(records, desc)
    first = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    latencies = [t.onset_latency_ms for t in touches if t.onset_latency_ms is not None]
    lockstep = metadata.get("session", {}).get("timing") == "lockstep"
    if lockstep:  # stamps are control cycles of simulated time: the "latency" is the cycle it fell in
        for t in touches:
            t.onset_latency_ms = None
    print(f"\nRecording {path}: {len(records)} messages")
    print(table.render([c.header for c in chosen], table.touch_rows(touches, first, chosen), width))
    if any(t.reflex_seq for t in touches):
        print("\n" + table.render(analysis.QUALITY_HEADER, analysis.quality_rows([analysis.quality(touches)]), width))
    if lockstep and latencies:
        print(f"\n{len(latencies)} reflexes on simulated time (lockstep): each began within the control cycle of "
              "its skin sample, by construction; no latency is measured here (`nwr demo` or `nwr bench` live)")
    elif latencies:
        import numpy as np

        print(f"\nreflex onset latency over {len(latencies)} reflexes: median {np.median(latencies):.2f} ms, "
              f"worst {max(latencies):.2f} ms")
    try:
        written = table.write_csv(table.csv_path(path), touches, first)
        print(f"\nevery column of every touch: {written}")
    except OSError as e:
        print(f"\nthe touches' CSV was not written ({e})")
    if script_name:
        return _compare_with_script(touches, script_name, desc, first, profile)
    return 0


def _compare_with_script(touches: list[Any], script_name: str, desc: Any, t0_ns: int, profile: Profile) -> int:
    """Every scripted touch seen on its pad at its time, with a reflex exactly when G(peak) > 0."""
    from nwr.services.gain.core import GainEstimator

    estimator = GainEstimator(profile.gain, desc.pads)
    script = load_script(script_name)
    mismatches = []
    for touch in script.touch:
        pad = desc.pad(touch.pad)
        _, expected_gain = estimator.gain(pad.id, touch.peak_hpa)
        window = (touch.start_s - 0.2, touch.start_s + touch.ramp_s + 0.3)
        match = next((t for t in touches if t.pad == pad.id and window[0] <= (t.start_ns - t0_ns) / 1e9 <= window[1]),
                     None)
        if match is None:
            mismatches.append(f"touch on {pad.name} at {touch.start_s} s was not seen")
        elif (match.reflex_seq > 0) != (expected_gain > 0):
            mismatches.append(f"touch on {pad.name} at {touch.start_s} s ({touch.peak_hpa} hPa): "
                              f"expected {'a' if expected_gain > 0 else 'no'} reflex")
    if mismatches:
        print("\nthe recording does NOT match its script:\n  " + "\n  ".join(mismatches))
        return 1
    print(f"\nall {len(script.touch)} scripted touches as expected "
          f"({sum(1 for t in touches if t.reflex_seq)} reflexes, none from sub-threshold touches)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("summary", help="print the per-touch table of a recording")
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--script", help="touch script to compare the recording with")
    add_table_arguments(p)
    p.set_defaults(handler=lambda args: print_summary(Path(args.file), args.script, profile_for(args),
                                                      wide=args.wide, columns=args.columns))


def add_table_arguments(p: argparse.ArgumentParser) -> None:
    from nwr.services.tools.recordings.table import NAMES

    p.add_argument("--wide", action="store_true",
                   help="print every column of the per-touch table (default: the essential ones, which fit 120 "
                        "columns; every column is written to <recording>.touches.csv either way)")
    p.add_argument("--columns", metavar="C1,C2,...",
                   help=f"print these columns of the per-touch table, in this order: {', '.join(NAMES)}")
