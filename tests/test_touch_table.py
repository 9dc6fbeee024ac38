"""The per-touch table fits a 120-column terminal by default, prints every column on request, and is written in
full as CSV beside the recording."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from nwr.common.config import load_profile
from nwr.common.errors import ConfigError
from nwr.common.robot import load_description
from nwr.services.tools.recordings import analysis, table
from nwr.services.tools.recordings.replay import simulate
from nwr.services.tools.recordings.summary import print_summary

DATA = Path(__file__).parent / "data"
DESC = load_description()


def widest_touches() -> list[analysis.TouchSummary]:
    """A touch of every pad in a long session, each figure as wide as a session's gets (a withdrawal short of a
    metre, a 100 ms onset on a loaded machine), the longest pad name as the other pad."""
    longest = max(DESC.pads, key=lambda p: len(p.name)).name
    return [analysis.TouchSummary(pad.id, pad.name, pad.region, 0, 1, 0, 1, peak_hpa=125.0, level=4, gain=1.0,
                                  reflex_seq=pad.id + 1, onset_latency_ms=99.99, withdrawal_mm=999.9,
                                  toward_mm=999.9, corrected=True, withdraws=False, other_approach_mm=999.9,
                                  other_pad=longest, peak_speed_m_s=1.234, peak_toward_m_s=1.234, returns_into=12,
                                  back_mm=-999.9, return_speed_m_s=1.234, resumed_after_s=99.99)
            for pad in DESC.pads]


def body(text: str) -> list[str]:
    """The table's rows: the lines below its header's rule."""
    lines = text.splitlines()
    rule = next(i for i, line in enumerate(lines) if line.startswith("---"))
    return lines[rule + 1:]


def test_the_essential_columns_of_the_widest_touches_fit_120_columns() -> None:
    chosen = table.columns()
    text = table.render([c.header for c in chosen], table.touch_rows(widest_touches(), -999_990_000_000, chosen))
    lines = text.splitlines()
    assert max(map(len, lines)) <= 120, text
    # Not by wrapping: one line per touch below the header and its rule.
    assert len(body(text)) == len(DESC.pads), text
    assert lines[-1].split()[:2] == ["999.99", DESC.pads[-1].name] and "999.9 cannot" in lines[-1]


def test_wide_prints_every_column_and_columns_a_chosen_few_in_their_order() -> None:
    touches = widest_touches()[:2]
    wide = table.columns(wide=True)
    assert [c.name for c in wide] == table.NAMES
    text = table.render([c.header for c in wide], table.touch_rows(touches, 0, wide), table.UNBOUNDED)
    assert len(body(text)) == len(touches) and max(map(len, text.splitlines())) > 120  # nothing wrapped
    for word in ("region", "back", "into", "return", "toward", "(m/s)"):
        assert word in text
    few = table.columns(names="withdrawal, pad")
    assert [c.name for c in few] == ["withdrawal", "pad"]
    header = table.render([c.header for c in few], table.touch_rows(touches, 0, few)).splitlines()[:2]
    assert " ".join(header).split() == ["withdrawal", "(mm)", "pad"]
    with pytest.raises(ConfigError, match="nosuch.*withdrawal"):
        table.columns(names="t,nosuch")


def test_a_summary_prints_the_essential_columns_and_writes_every_one_as_csv(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture) -> None:
    profile = load_profile()
    path, _, _ = simulate(profile, str(DATA / "short.toml"), "cartesian", tmp_path / "short.mcap")
    assert print_summary(path, str(DATA / "short.toml"), profile) == 0
    out = capsys.readouterr().out
    printed = out.split("messages\n", 1)[1].split("\n\n", 1)[0]  # the per-touch table
    assert len(body(printed)) == 4 and max(map(len, printed.splitlines())) <= 120, out
    assert "withdrawal" in out and "region" not in out and "return" not in out
    written = tmp_path / "short.touches.csv"
    assert f"every column of every touch: {written}" in out
    with written.open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == table.CSV_FIELDS
    assert [r["name"] for r in rows] == ["upper_arm_top", "forearm_top", "wrist_2", "elbow_outer"]
    assert [r["reflex_seq"] != "0" for r in rows] == [False, True, True, False]
    reflex = rows[1]
    assert float(reflex["withdrawal_mm"]) > 1.0 and float(reflex["return_speed_m_s"]) > 0.0
    assert reflex["onset_latency_ms"] == ""  # lockstep measures no latency, in the CSV as in the table
    assert rows[0]["withdrawal_mm"] == "" and float(rows[0]["t_s"]) == pytest.approx(1.96, abs=0.05)

    assert print_summary(path, None, profile, wide=True) == 0
    wide = capsys.readouterr().out
    assert "region" in wide and "return" in wide
    assert body(wide.split("messages\n", 1)[1])[0].split()[:3] == ["1.96", "upper_arm_top", "upper_arm"]
