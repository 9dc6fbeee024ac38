"""The per-touch table: its columns as data, printed to fit the terminal, written in full as CSV.

By default ``nwr summary`` and ``nwr demo`` print the essential columns,
which fit a 120-column terminal (the effective-mass gain model's predicted
impact force, ``impact``, and effective mass, ``mass``, at each onset are not
among them: a line below the table gives their largest; nor are a physics
world's measured figures, :data:`WORLD_COLUMNS`, which ``nwr summary``
prints in a table of their own); ``--wide`` prints every column and
``--columns`` a chosen few (by the names :data:`COLUMNS` gives). The tables
are rendered with ``rich``: a header's unit goes on a line of its own, and a
terminal narrower than the table wraps its cells rather than the lines.
Every figure of every touch is also written beside the recording as
``<recording>.touches.csv`` (:func:`write_csv`), one row per touch.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
import shutil
import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from nwr.common.errors import ConfigError
from nwr.services.tools.recordings.analysis import TouchSummary, cell

DEFAULT_WIDTH = 120  # the width printed when the output is not a terminal (a pipe, a file, a test)
UNBOUNDED = 1000  # --wide into a pipe or a file: nothing wraps


@dataclass(frozen=True)
class Column:
    name: str  # what --columns takes
    header: str  # "label (unit)": the unit is printed on a line of its own
    value: Callable[[TouchSummary, int], str]  # the cell of a touch, given the recording's first skin stamp
    essential: bool  # printed by default


def _other_pad(t: TouchSummary, _: int) -> str:
    return "-" if t.other_approach_mm is None else f"{t.other_approach_mm:.1f} {t.other_pad}"


COLUMNS = [
    Column("t", "t (s)", lambda t, t0: f"{(t.start_ns - t0) / 1e9:.2f}", True),
    Column("pad", "pad", lambda t, _: t.name, True),
    Column("region", "region", lambda t, _: t.region, False),
    Column("peak", "peak (hPa)", lambda t, _: f"{t.peak_hpa:.1f}", True),
    Column("pl", "PL", lambda t, _: str(t.level), True),
    Column("gain", "gain", lambda t, _: f"{t.gain:.3f}", True),
    Column("reflex", "reflex", lambda t, _: "yes" if t.reflex_seq else "no" if t.reflex_known else "?", True),
    Column("onset", "onset (ms)", lambda t, _: cell(t.onset_latency_ms, ".2f"), True),
    Column("withdrawal", "withdrawal (mm)",
           lambda t, _: cell(t.withdrawal_mm, ".1f") + ("" if t.withdraws else " cannot"), True),
    Column("toward", "toward (mm)", lambda t, _: cell(t.toward_mm, ".1f") + ("*" if t.corrected else ""), True),
    Column("other", "other pad closer (mm)", _other_pad, True),
    Column("peak_speed", "peak (m/s)", lambda t, _: cell(t.peak_speed_m_s, ".3f"), True),
    Column("toward_speed", "toward (m/s)", lambda t, _: cell(t.peak_toward_m_s, ".3f"), False),
    Column("back_into", "back into", lambda t, _: str(t.returns_into) if t.reflex_seq else "-", False),
    Column("back_to", "back to (mm)", lambda t, _: cell(t.back_mm, ".1f"), False),
    Column("return_speed", "return (m/s)", lambda t, _: cell(t.return_speed_m_s, ".3f"), False),
    Column("resumed", "resumed (s)", lambda t, _: cell(t.resumed_after_s, ".2f"), True),
    # Why the reflex's motion is not its strategy's plain withdrawal (ReflexInfo.reason), what the joints allowed
    # it at full gain (reach_mm), and its retreat check of the other touched pads (their worst, planned).
    Column("why", "why", lambda t, _: t.reason or "-", False),
    Column("reach", "reach (mm)", lambda t, _: cell(t.reach_mm, ".1f"), False),
    Column("others_planned", "others planned toward (mm)",
           lambda t, _: "-" if t.planned_others_toward_mm is None
           else f"{t.planned_others_toward_mm:.1f} {t.planned_others_pad}", False),
    Column("impact", "impact (N)", lambda t, _: cell(t.impact_n, ".0f"), False),
    Column("mass", "mass (kg)", lambda t, _: cell(t.effective_mass_kg, ".1f"), False),
    # A physics world's (nwr summary prints them in a table of their own when the recording has them).
    Column("pressed", "pad toward finger (mm)", lambda t, _: cell(t.pressed_toward_mm, ".1f"), False),
    Column("peak_force", "peak force (N)", lambda t, _: cell(t.peak_force_n, ".1f"), False),
    Column("into", "into finger (mm)", lambda t, _: cell(t.into_finger_mm, ".1f"), False),
    Column("pressure", "peak pressure (N/cm^2)", lambda t, _: cell(t.peak_pressure_n_cm2, ".1f"), False),
    Column("energy", "energy (mJ)", lambda t, _: cell(None if t.energy_j is None else 1e3 * t.energy_j, ".1f"),
           False),
    Column("of_limit", "of ISO limit (%)", lambda t, _: cell(None if t.of_limit is None else 100 * t.of_limit,
                                                             ".0f"), False),
]
WORLD_COLUMNS = ("pressed", "peak_force", "into", "pressure", "energy", "of_limit")
NAMES = [c.name for c in COLUMNS]


def columns(wide: bool = False, names: str | None = None) -> list[Column]:
    """The columns to print: ``names`` (comma-separated, in their order), else every one (``wide``), else the
    essential ones."""
    if names:
        chosen = [n.strip() for n in names.split(",") if n.strip()]
        unknown = [n for n in chosen if n not in NAMES]
        if unknown:
            raise ConfigError(f"--columns names {', '.join(unknown)}; the columns are {', '.join(NAMES)}")
        return [next(c for c in COLUMNS if c.name == n) for n in chosen]
    return [c for c in COLUMNS if wide or c.essential]


def touch_rows(touches: list[TouchSummary], t0_ns: int, chosen: list[Column]) -> list[list[str]]:
    return [[c.value(t, t0_ns) for c in chosen] for t in touches]


def width(wide: bool = False) -> int:
    """The width to print in: the terminal's; else COLUMNS, else 120 (``wide``: unbounded)."""
    if sys.stdout.isatty():
        return shutil.get_terminal_size((DEFAULT_WIDTH, 24)).columns
    columns_env = os.environ.get("COLUMNS", "")
    if columns_env.isdigit() and not wide:
        return int(columns_env)
    return UNBOUNDED if wide else DEFAULT_WIDTH


def _header(header: str, cells: list[str]) -> str:
    """``header`` wrapped at spaces to its column's width (its widest cell or word), its unit on a line of its own:
    the column is no wider than its figures."""
    label, sep, unit = header.partition(" (")
    unit = f"({unit}" if sep else ""
    width = max([len(c) for c in cells] + [len(w) for w in header.split()])
    lines = textwrap.wrap(label, width, break_long_words=False) + ([unit] if unit else [])
    return "\n".join(lines)


def render(header: list[str], rows: list[list[str]], width: int = DEFAULT_WIDTH) -> str:
    """The table as text at most ``width`` characters wide, plain (no colours, no trailing spaces)."""
    from rich import box
    from rich.console import Console
    from rich.table import Table

    # The header underlined with ASCII dashes, one run per column, and nothing else drawn: plain text anywhere.
    ruled = box.Box("    \n    \n -  \n    \n    \n    \n    \n    \n", ascii=True)
    # Two spaces between columns: the divider (a space) and one of padding.
    table = Table(box=ruled, show_edge=False, pad_edge=False, padding=(0, 0, 0, 1), header_style="",
                  highlight=False)
    for i, h in enumerate(header):
        table.add_column(_header(h, [r[i] for r in rows]), justify="right", overflow="fold")
    for row in rows:
        table.add_row(*row)
    out = io.StringIO()
    Console(file=out, width=width, color_system=None, emoji=False, markup=False, highlight=False,
            force_terminal=False, force_jupyter=False, soft_wrap=False).print(table)
    return "\n".join(line.rstrip() for line in out.getvalue().splitlines())


def csv_path(recording: Path) -> Path:
    return recording.with_name(recording.stem + ".touches.csv")


CSV_FIELDS = ["t_s", *(f.name for f in dataclasses.fields(TouchSummary))]


def write_csv(path: Path, touches: list[TouchSummary], t0_ns: int) -> Path:
    """Every field of every touch, one row per touch (an empty cell: none), ``t_s`` from the first skin sample."""
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_FIELDS)
        for t in touches:
            values = dataclasses.asdict(t)
            writer.writerow([f"{(t.start_ns - t0_ns) / 1e9:.3f}",
                             *("" if values[k] is None else values[k] for k in CSV_FIELDS[1:])])
    return path
