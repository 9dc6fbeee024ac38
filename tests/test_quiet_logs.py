"""Quiet by default: a loop late by a few cycles on a busy machine is counted, not warned about; repeated warnings
are summed up with their count, not printed one per event; `nwr verify` prints its findings, not the recorded
run's log."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest

from nwr.common import pacing
from nwr.common.config import load_profile
from nwr.common.node import RepeatedLog
from nwr.common.pacing import Rate
from nwr.services.tools.recordings import verify
from nwr.services.tools.recordings.replay import simulate

DATA = Path(__file__).parent / "data"
S = 1_000_000_000


def late_by(rate: Rate, cycles: int) -> None:
    """The loop wakes ``cycles`` cycles after its next deadline and drops the cycles it missed."""
    assert rate.skip(rate.next_ns + cycles * rate.period_ns) == cycles + 1


def test_a_loop_late_by_a_few_cycles_is_counted_and_summed_up_at_info(caplog: pytest.LogCaptureFixture) -> None:
    rate = Rate(500, "bridge")
    rate.restart(10 * S)
    with caplog.at_level(logging.INFO, logger="nwr.common.pacing"):
        first = rate.next_ns
        while rate.next_ns < first + 59 * S:  # a loaded machine: 8 ms late five times a second, for a minute
            late_by(rate, 3)
            rate.restart(rate.next_ns + S // 5)
        assert not caplog.records  # not one line per overrun, nor a warning
        for _ in range(50):
            late_by(rate, 3)
            rate.restart(rate.next_ns + S // 5)
        assert len(caplog.records) == 1 and caplog.records[0].levelno == logging.INFO
        minute = re.fullmatch(r"bridge loop overran (\d+) times in the last 60 s \(0 by more than 10 cycles\), the "
                              r"worst by 8\.0 ms \((\d+) overruns so far\)", caplog.records[0].getMessage())
        assert minute is not None and 280 < int(minute[1]) == int(minute[2]) < 300, caplog.records[0].getMessage()
        rate.summary()  # the rest of the run, at the end
    assert [r.levelno for r in caplog.records] == [logging.INFO, logging.INFO]
    assert f"overran {rate.overruns - int(minute[1])} times" in caplog.records[1].getMessage()


def test_a_loop_late_by_more_than_its_tolerance_warns_once_then_sums_up(caplog: pytest.LogCaptureFixture) -> None:
    rate = Rate(500, "planner")
    rate.restart(10 * S)
    with caplog.at_level(logging.INFO, logger="nwr.common.pacing"):
        for _ in range(20):
            late_by(rate, pacing.LATE_PERIODS + 5)  # 30 ms late: a fault
        assert [r.getMessage() for r in caplog.records] == ["planner loop overran by 32.0 ms (1 overruns so far)"]
        rate.restart(rate.next_ns + 61 * S)
        late_by(rate, 1)
    assert [r.levelno for r in caplog.records] == [logging.WARNING, logging.WARNING]
    assert caplog.records[1].getMessage().startswith(
        "planner loop overran 19 times in the last 62 s (19 by more than 10 cycles), the worst by 32.0 ms")


def test_repeated_diagnostics_print_a_line_a_minute_with_their_count(caplog: pytest.LogCaptureFixture) -> None:
    repeats = RepeatedLog()
    with caplog.at_level(logging.WARNING, logger="nwr.common.node"):
        for i in range(30):  # once a second (the diag key's own rate limit), 3 suppressed before each
            repeats.log("warning", "stale_command", f"command {i} is late", 4, 10 * S + i * S)
        repeats.log("error", "planner_lost", "planner 'a' lost", 1, 20 * S)
        assert [r.getMessage() for r in caplog.records] == ["[stale_command] command 0 is late (3 more like it "
                                                            "in the last 0 s)", "[planner_lost] planner 'a' lost"]
        repeats.log("warning", "stale_command", "command 70 is late", 1, 80 * S)
        repeats.log("warning", "stale_command", "command 71 is late", 1, 81 * S)
        repeats.flush(90 * S)
        repeats.flush(91 * S)  # nothing left
    lines = [r.getMessage() for r in caplog.records]
    assert lines[2:] == ["[stale_command] command 70 is late (116 more like it in the last 70 s)",
                         "[stale_command] 1 more like it in the last 10 s, the last: command 71 is late"]
    assert caplog.records[1].levelno == logging.ERROR


def test_verify_prints_its_findings_not_the_recorded_run_s_log(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    path, _, _ = simulate(load_profile(), str(DATA / "short.toml"), "cartesian", tmp_path / "short.mcap")
    take = Rate.take

    def overrunning(self: Rate, now_ns: int, limit: int | None = None) -> int:  # the recorded run's overruns
        logging.getLogger("nwr.common.pacing").warning("%s loop overran by 3.0 ms", self.name)
        return take(self, now_ns, limit)

    monkeypatch.setattr(Rate, "take", overrunning)
    with caplog.at_level(logging.DEBUG):
        results = verify.verify(path)
        logging.getLogger("nwr.common.pacing").warning("after the re-run")  # logging works again
    assert [r.verdict for r in results] == ["identical"] * 4
    assert [r.getMessage() for r in caplog.records] == ["after the re-run"]
