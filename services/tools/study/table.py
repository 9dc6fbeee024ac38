"""The whole study as one table: a row per block, what its recording measured beside what was answered.

``nwr study analyze`` writes it as ``study.csv`` and ``study.parquet`` for the
lab's own analysis (pandas, R, a spreadsheet): one row per block that is
planned (``nwr study``) or answered, keyed by participant and block. Its
columns, in order (docs/study.md describes each):

- the block: participant, order, block, condition and its label, recording;
- the recording's figures (``analysis.summarize`` and the reflex quality
  table's flags, ``analysis.quality``): touches, reflexes, onset latency,
  withdrawal, speeds, jerk, approaches; empty where the recording is missing
  or unreadable (``recording_problem`` says which);
- the block's answers: each subscale's score (reversed items flipped), each
  rated item as answered (1..points, reversed items not flipped);
- the participant's final form: each forced choice (a condition or "none").

Open answers (free text) are never in it. The CSV neutralises any text a
spreadsheet would run as a formula (``store.csv_cell``); Parquet keeps the
types (integers, floats, booleans, text; missing values as nulls).
"""

from __future__ import annotations

import csv
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nwr.common.questionnaire import Questionnaire
from nwr.services.tools.study.store import Block, FinalAnswer, Rating, csv_row

CSV_NAME = "study.csv"
PARQUET_NAME = "study.parquet"


@dataclass(frozen=True)
class Column:
    name: str
    kind: str  # "str", "int", "float" or "bool"
    doc: str


def _median(xs: list[float]) -> float | None:
    return float(np.median(xs)) if xs else None


def _max(xs: list[float]) -> float | None:
    return max(xs) if xs else None


def _min(xs: list[float]) -> float | None:
    return min(xs) if xs else None


def _some(values: Sequence[float | None]) -> list[float]:
    return [float(v) for v in values if v is not None]


# The recording's figures: (column, kind, what it is, how it comes from the block's touches and quality row).
MEASURES: list[tuple[Column, Callable[[list[Any], Any], Any]]] = [
    (Column("touches", "int", "touches in the recording (each a pad's contact, with or without a reflex)"),
     lambda ts, q: len(ts)),
    (Column("reflexes", "int", "touches that started a reflex"), lambda ts, q: q.reflexes),
    (Column("reflexes_cannot_withdraw", "int", "reflexes whose planner found no motion moving the touched pad "
                                               "away (it held still)"),
     lambda ts, q: sum(1 for t in ts if t.reflex_seq and not t.withdraws)),
    (Column("onset_ms_median", "float", "median onset latency over the reflexes, ms (skin sample stamped in the "
                                        "gateway -> first command of the reflex accepted by the bridge)"),
     lambda ts, q: _median(_some([t.onset_latency_ms for t in ts if t.reflex_seq]))),
    (Column("onset_ms_max", "float", "worst onset latency, ms"),
     lambda ts, q: _max(_some([t.onset_latency_ms for t in ts if t.reflex_seq]))),
    (Column("withdrawal_mm_median", "float", "median withdrawal of the touched pad along its outward normal, mm"),
     lambda ts, q: q.withdrawal_median_mm),
    (Column("withdrawal_mm_min", "float", "smallest withdrawal of a pad that can withdraw, mm"),
     lambda ts, q: q.withdrawal_min_mm),
    (Column("toward_mm_max", "float", "the touched pad's furthest move toward the contact during a reflex, mm"),
     lambda ts, q: q.worst_toward_mm),
    (Column("pad_toward_gt_5mm", "int", "reflexes whose touched pad moved more than 5 mm toward the contact"),
     lambda ts, q: q.approached),
    (Column("other_pad_approach_mm_max", "float", "any other pad's largest approach to a contact point, mm"),
     lambda ts, q: q.worst_other_mm),
    (Column("peak_speed_m_s_median", "float", "median over the reflexes of the arm's fastest point (pads, elbow, "
                                              "flange) over the whole withdrawal, m/s"),
     lambda ts, q: _median(_some([t.peak_speed_m_s for t in ts if t.reflex_seq]))),
    (Column("peak_speed_m_s_max", "float", "the block's fastest withdrawal, m/s"),
     lambda ts, q: _max(_some([t.peak_speed_m_s for t in ts if t.reflex_seq]))),
    (Column("peak_toward_m_s_max", "float", "the fastest speed of the arm toward a contact during a withdrawal, "
                                            "m/s (the bridge limits it to 0.25)"),
     lambda ts, q: _max(_some([t.peak_toward_m_s for t in ts if t.reflex_seq]))),
    (Column("peak_jerk_m_s3_median", "float", "median over the reflexes of the touched pad's peak jerk, m/s^3"),
     lambda ts, q: q.peak_jerk_m_s3),
    (Column("returns_into", "int", "reflexes begun again on a pad while its touch lasted, from a return or the "
                                   "task: the arm came back into the finger (0 is the goal)"),
     lambda ts, q: sum(t.returns_into for t in ts if t.reflex_seq)),
    (Column("resumed_s_median", "float", "median time from a reflex's onset to the planner back in its task, s"),
     lambda ts, q: _median(_some([t.resumed_after_s for t in ts if t.reflex_seq]))),
    (Column("any_touched_pad_toward_gt_5mm", "int", "touches with a gain (whichever reflex ran) whose pad moved "
                                                    "more than 5 mm toward where it was touched while it lasted"),
     lambda ts, q: q.any_toward),
    (Column("back_past_recent_touch_gt_10mm", "int", "touches (any the skin felt, with a gain or not) the arm "
                                                     "went back through by more than 10 mm within 3 s of their end"),
     lambda ts, q: q.back_past),
]

# The bridge during the block (analysis.BridgeHealth), beside the touches' figures.
HEALTH_COLUMNS = [
    Column("commands_rejected", "int", "commands the bridge rejected during the block (jumps, out of order, "
                                       "another planner's)"),
    Column("arm_stops", "int", "times the bridge went from following commands to stopping the arm (stale skin "
                               "or commands, a lost planner, a protective stop, a disconnection, ...)"),
    Column("degraded", "bool", "commands rejected or the arm stopped: the block was not the condition as designed "
                               "(nwr study analyze --exclude-degraded leaves its answers out of the tests)"),
]

BLOCK_COLUMNS = [
    Column("participant", "str", "the participant's code (pseudonymous)"),
    Column("order", "int", "the participant's counterbalanced order (nwr study --order)"),
    Column("block", "int", "the block's position in the session, from 1"),
    Column("condition", "str", "the reflex strategy of the block"),
    Column("condition_label", "str", "its label in the questionnaire (UR, LR, CR, ...)"),
    Column("recording", "str", "the block's recording, relative to the store's folder"),
    Column("recording_read", "bool", "whether the recording was read (false: the figures are empty)"),
    Column("recording_problem", "str", "empty, or why not: missing, unreadable (why), not analysed"),
]
ANSWER_COLUMNS = [
    Column("answered", "bool", "whether the block's questionnaire was submitted"),
    Column("answered_at", "str", "when (UTC, ISO 8601)"),
]


def columns(q: Questionnaire) -> list[Column]:
    """Every column of the table for questionnaire ``q``, in order."""
    scales = [Column(f"score_{s.id}", "float", f"{s.name}: the mean of its items, reversed items flipped "
                                              f"({q.points + 1} - x)") for s in q.scales()]
    items = [Column(f"item_{i}", "int", f"item {i} as answered, 1..{q.points}") for i in q.rated_items()]
    choices = [Column(f"choice_{c.id}", "str", f"the participant's answer to {c.text!r}: a condition or "
                                               "'none'") for c in q.choice]
    return [*BLOCK_COLUMNS, *(c for c, _ in MEASURES), *HEALTH_COLUMNS, *ANSWER_COLUMNS, *scales, *items, *choices]


def block_table(q: Questionnaire, planned: list[Block], ratings: list[Rating], finals: list[FinalAnswer],
                measured: dict[tuple[str, int], Any] | None) -> list[dict[str, Any]]:
    """One row per block (planned or answered), sorted by participant and block: ``columns(q)`` -> value
    (None: none). ``measured``: (participant, block) -> its ``analysis.BlockMeasures``; None: not analysed."""
    from nwr.services.tools.recordings import analysis

    rows: dict[tuple[str, int], dict[str, Any]] = {}
    for b in planned:
        rows[(b.participant, b.block)] = {"participant": b.participant, "order": b.order, "block": b.block,
                                          "condition": b.condition, "recording": b.recording,
                                          "answered_at": b.answered_at}
    values: dict[tuple[str, int], dict[str, int]] = defaultdict(dict)
    for r in ratings:
        row = rows.setdefault((r.participant, r.block), {})
        row.update(participant=r.participant, order=r.order, block=r.block, condition=r.condition,
                   recording=r.recording, answered_at=r.submitted_at)
        values[(r.participant, r.block)][r.item] = r.value
    choices: dict[str, dict[str, str]] = defaultdict(dict)
    for a in finals:
        if a.kind == "choice":
            choices[a.participant][a.item] = a.text
    out = []
    for key in sorted(rows):
        row = rows[key]
        row["condition_label"] = q.label(row["condition"])
        bm = None if measured is None else measured.get(key)
        if bm is None:
            row["recording_read"], row["recording_problem"] = False, "not analysed"
        elif bm.problem:
            row["recording_read"], row["recording_problem"] = False, bm.problem
        else:
            row["recording_read"], row["recording_problem"] = True, ""
            quality = analysis.quality(bm.touches, row["condition"])
            for column, measure in MEASURES:
                row[column.name] = measure(bm.touches, quality)
            if bm.health is not None:
                row["commands_rejected"] = bm.health.rejected
                row["arm_stops"] = sum(bm.health.stops.values())
                row["degraded"] = bm.health.degraded
        answers = values.get(key, {})
        row["answered"] = bool(answers)
        if not answers:
            row["answered_at"] = None
        for scale in q.scales():
            given = [q.points + 1 - answers[i] if i in scale.reversed else answers[i] for i in scale.items
                     if i in answers]
            row[f"score_{scale.id}"] = float(np.mean(given)) if len(given) == len(scale.items) else None
        for item in q.rated_items():
            row[f"item_{item}"] = answers.get(item)
        for c in q.choice:
            row[f"choice_{c.id}"] = choices[row["participant"]].get(c.id)
        out.append({c.name: row.get(c.name) for c in columns(q)})
    return out


def _csv_value(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return value


def write_csv(q: Questionnaire, rows: list[dict[str, Any]], path: Path) -> Path:
    names = [c.name for c in columns(q)]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(names)
        for row in rows:
            w.writerow(csv_row([_csv_value(row[n]) for n in names]))
    return path


def write_parquet(q: Questionnaire, rows: list[dict[str, Any]], path: Path) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"str": pa.string(), "int": pa.int64(), "float": pa.float64(), "bool": pa.bool_()}
    cols = columns(q)
    schema = pa.schema([pa.field(c.name, types[c.kind], nullable=True, metadata={"doc": c.doc}) for c in cols])
    table = pa.table({c.name: pa.array([r[c.name] for r in rows], type=types[c.kind]) for c in cols},
                     schema=schema)
    pq.write_table(table, path)
    return path
