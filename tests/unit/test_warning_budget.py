"""A service's warnings of one text at a bounded rate (runner.WarningBudget): a flood of
refused input is counted in full by the metrics, not logged a line each."""

from __future__ import annotations

import logging

import pytest

from swarmrec.runtime import runner
from swarmrec.runtime.runner import WarningBudget


def _record(msg: str, level: int = logging.WARNING) -> logging.LogRecord:
    return logging.LogRecord("t", level, __file__, 1, msg, None, None)


def test_at_most_burst_warnings_of_one_text_a_window_and_the_next_says_how_many_were_not(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    now = [100.0]
    monkeypatch.setattr(runner.time, "monotonic", lambda: now[0])
    budget = WarningBudget(burst=3, window_s=10.0)
    passed = [budget.filter(_record("rejected request")) for _ in range(1500)]
    assert sum(passed) == 3 and passed[:3] == [True] * 3
    # Another text has its own budget; errors always pass.
    assert budget.filter(_record("subscription queue full"))
    assert all(budget.filter(_record("rejected request", logging.ERROR)) for _ in range(10))
    now[0] += 10.0  # a new window
    first = _record("rejected request")
    assert budget.filter(first)
    assert first.fields == {"not_logged": 1497}  # type: ignore[attr-defined]
    second = _record("rejected request")
    assert budget.filter(second) and not hasattr(second, "fields")


def test_a_service_logger_bounds_a_flood_of_warnings(capsys: pytest.CaptureFixture[str]) -> None:
    log = runner.service_logger("verifier", 3, "INFO")
    for i in range(1500):
        log.warning("rejected request", extra={"fields": {"endpoint": "store", "n": i}})
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == runner.WARNING_BURST
