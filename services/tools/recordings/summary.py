"""``nwr summary``: the per-touch table of a recording, and whether it matches its touch script."""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path
from typing import Any

from nwr.common.config import Profile
from nwr.common.launch import load_script
from nwr.services.profile import load_profile, profile_for


def print_summary(path: Path, script_name: str | None, profile: Profile | None = None, *, wide: bool = False,
                  columns: str | None = None) -> int:
    """Print the per-touch table of the recording ``path`` (the essential columns, or every one: ``wide``, or
    ``columns``: names, comma-separated) and write every column to ``<recording>.touches.csv``."""
    from nwr.common.recordings import read_recording
    from nwr.common.robot import load_description
    from nwr.common.skin import entry_pads, load_skin
    from nwr.services.tools.recordings import analysis, table

    chosen = table.columns(wide, columns)  # an unknown column is refused before the recording is read
    width = table.width(wide)

    records, metadata = read_recording(path)
    profile = profile or load_profile(None)
    desc = load_description(profile.robot.description or None)
    skin = load_skin(profile, desc)
    touches = analysis.summarize(records, desc, entry_pads=entry_pads(skin, desc.pads) if skin is not None else None)
    first = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    latencies = [t.onset_latency_ms for t in touches if t.onset_latency_ms is not None]
    lockstep = is_lockstep(metadata)
    physics = any(t.peak_force_n is not None for t in touches)
    notes = complete(touches, records, metadata, profile, desc)
    print(f"\nRecording {path}: {len(records)} messages")
    for note in notes:
        print(textwrap.fill(note, table.DEFAULT_WIDTH, subsequent_indent="  "))
    print(table.render([c.header for c in chosen], table.touch_rows(touches, first, chosen), width))
    if physics:  # the physics world's fingers: the force on each, how far the arm pushed it back
        fingers = [c for c in table.COLUMNS if c.name in ("t", "pad", *table.WORLD_COLUMNS)]
        print("\nthe physics world's fingers:\n" + table.render([c.header for c in fingers],
                                                                table.touch_rows(touches, first, fingers), width))
        for note in iso_notes(touches):
            print(textwrap.fill(note, table.DEFAULT_WIDTH, subsequent_indent="  "))
    if any(t.reflex_seq for t in touches):
        rows, k = analysis.quality_rows([analysis.quality(touches)]), analysis.CONTACT_QUALITY_FROM
        print("\n" + table.render(analysis.QUALITY_HEADER[:k], [r[:k] for r in rows], width))
        header = analysis.QUALITY_HEADER
        print("\n" + table.render(header[:1] + header[k:], [r[:1] + r[k:] for r in rows], width))
    if physics:
        print("\n" + table.render(analysis.WORLD_QUALITY_HEADER,
                                   analysis.world_quality_rows([analysis.quality(touches)]), width))
    predicted = [t for t in touches if t.impact_n is not None]
    if predicted:
        top = max(predicted, key=lambda t: t.impact_n or 0.0)
        print(f"\npredicted impact force at the onset ({len(predicted)} touches, the effective-mass gain model): "
              f"largest {top.impact_n:.0f} N on {top.name} (effective mass {top.effective_mass_kg:.1f} kg); "
              "per touch: --columns t,pad,gain,impact,mass,reflex")
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
        return _compare_with_script(touches, script_name, desc, first, profile, physics=physics)
    return 0


def iso_notes(touches: list[Any]) -> list[str]:
    """A line per ISO/TS 15066 body area the physics world's touches were judged by: its limits, and the touches
    beyond them."""
    from nwr.services.worlds.people import ISO_TS_15066, KINDS

    notes = []
    for area in sorted({t.body_area for t in touches if t.body_area}):
        r = ISO_TS_15066[area]
        mine = [t for t in touches if t.body_area == area and t.of_limit is not None]
        over = [t for t in mine if (t.of_limit or 0.0) > 1.0]
        notes.append(f"of ISO limit: the larger of peak force and peak pressure as a share of ISO/TS 15066's "
                     f"quasi-static limits for {r.region}, {area.replace('_', ' ')} ({r.force_n:g} N, "
                     f"{r.pressure_n_cm2:g} N/cm^2; transient {r.transient_force_n:g} N, "
                     f"{r.transient_pressure_n_cm2:g} N/cm^2; a touch script's fingers are judged as "
                     f"{KINDS['finger'].area.replace('_', ' ')} unless a touch names its body_area; values "
                     f"compared with public reproductions of the table, not the standard's text, docs/worlds.md): "
                     + (f"{len(over)} of {len(mine)} touches beyond them" if over else f"all {len(mine)} within"))
    return notes


def is_lockstep(metadata: dict[str, dict[str, str]]) -> bool:
    """Was the recording made on simulated time (``nwr demo --fast``, ``nwr replay --fast``)?"""
    return metadata.get("session", {}).get("timing") == "lockstep"


def complete(touches: list[Any], records: list[Any], metadata: dict[str, dict[str, str]], profile: Profile,
             desc: Any) -> list[str]:
    """Say what the recording cannot tell, and fill in what can be computed instead; returns a line for each.

    - on simulated time (lockstep) a reflex's onset falls in its skin sample's control cycle by construction:
      no latency is measured, and none is shown;
    - without pain data (``skin/pain``: a real skin's imported recording) each touch's pain level and gain are
      computed from its peak pressure through the profile's gain model;
    - without a planner (no ``reflex/<name>/status``) whether a touch caused a reflex is unknown ("?").
    """
    from nwr.services.gain.core import GainEstimator

    notes: list[str] = []
    if is_lockstep(metadata):  # stamps are control cycles of simulated time: the "latency" is the cycle it fell in
        for t in touches:
            t.onset_latency_ms = None
    if not touches:
        return notes
    if not any(r.key == "skin/pain" for r in records):
        estimator = GainEstimator(profile.gain, desc.pads)
        for t in touches:
            t.level, t.gain = estimator.gain(t.pad, t.peak_hpa)
            t.pain_computed = True
        thresholds = "/".join(f"{x:g}" for x in profile.gain.thresholds_hpa)
        notes.append(f"no pain data (skin/pain) in this recording: PL and gain computed from each touch's peak "
                     f"pressure through the profile's {profile.gain.model} gain model (thresholds {thresholds} hPa)")
    if not any(r.key.startswith("reflex/") and r.key.endswith("/status") for r in records):
        for t in touches:
            t.reflex_known = False
        notes.append("no planner in this recording (no reflex/<name>/status): whether a touch caused a reflex "
                     "cannot be judged (reflex \"?\"); replay it against one: nwr replay FILE --fast --reflex NAME")
    return notes


def _within_a_reflex(touch: Any, touches: list[Any]) -> Any:
    """The touch on another pad whose reflex was under way while ``touch`` was felt (touches felt together, or
    one during another's withdrawal, get one reflex: the strongest contact's), or None."""
    def until(o: Any) -> float:  # the press, or the reflex until the task resumed if that was later
        return max(o.end_ns, o.start_ns + (o.resumed_after_s or 0.0) * 1e9)

    return next((o for o in touches if o.reflex_seq > 0 and o.pad != touch.pad and o.reflex_known
                 and o.start_ns <= touch.start_ns <= until(o)), None)


def _compare_with_script(touches: list[Any], script_name: str, desc: Any, t0_ns: int, profile: Profile, *,
                         physics: bool = False) -> int:
    """Every scripted touch seen on its pad at its time, with a reflex exactly when G(peak) > 0 (the effective-mass
    model: when G(peak) > 0 at the paper's thresholds, none when G(peak) = 0 at its floor, either in between: the
    touch's reflex then depends on how fast its pad moved).

    In a physics world (``physics``) the script gives each finger's force, not the pad's pressure: the arm's
    motion into a finger or away from it changes what the pad feels, so a reflex where the script's peak
    expects none (or none where it expects one) is the world's, reported but no mismatch."""
    from nwr.services.gain.core import GainEstimator

    estimator = GainEstimator(profile.gain, desc.pads)
    script = load_script(script_name, profile.robot.description)
    mismatches: list[str] = []
    differences: list[str] = []
    covered: list[str] = []
    for touch in script.touch:
        pad = desc.pad(touch.pad)
        least, most = estimator.gain_range(pad.id, touch.peak_hpa)
        window = (touch.start_s - 0.2, touch.start_s + touch.ramp_s + 0.3)
        match = next((t for t in touches if t.pad == pad.id and window[0] <= (t.start_ns - t0_ns) / 1e9 <= window[1]),
                     None)
        if match is None:
            mismatches.append(f"touch on {pad.name} at {touch.start_s} s was not seen")
        elif match.reflex_seq == 0 and least > 0 and (other := _within_a_reflex(match, touches)) is not None:
            covered.append(f"touch on {pad.name} at {touch.start_s} s: felt during the reflex of the touch on "
                           f"{desc.pads[other.pad].name} at {(other.start_ns - t0_ns) / 1e9:.2f} s, which went on")
        elif match.reflex_known and ((match.reflex_seq > 0 and most == 0) or (match.reflex_seq == 0 and least > 0)):
            (differences if physics else mismatches).append(
                f"touch on {pad.name} at {touch.start_s} s ({touch.peak_hpa} hPa, felt {match.peak_hpa:.1f}): "
                f"expected {'a' if least > 0 else 'no'} reflex")
    if covered:
        print("\na reflex already under way answered these touches (one reflex for touches felt together; "
              "docs/reflexes.md):\n  " + "\n  ".join(covered))
    if differences:
        print("\nthe physics world's pressures differ from the script's here (the arm moved into or away from "
              "the finger):\n  " + "\n  ".join(differences))
    if mismatches:
        print("\nthe recording does NOT match its script:\n  " + "\n  ".join(mismatches))
        return 1
    if not all(t.reflex_known for t in touches):
        print(f"\nall {len(script.touch)} scripted touches seen (their reflexes cannot be judged: no planner)")
        return 0
    if differences:
        print(f"\nall {len(script.touch)} scripted touches seen ({sum(1 for t in touches if t.reflex_seq)} "
              "reflexes)")
        return 0
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
