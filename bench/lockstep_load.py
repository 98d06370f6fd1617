"""What the balance benchmarks (bench_elastic.py, bench_scale.py) share: each shard's partial
queries read back from a run's report, and lock-step steps paced to a frame rate."""

from __future__ import annotations

import csv
import time
from collections import Counter
from pathlib import Path


def shard_loads(run_dir: Path, robots: int, first_step: int = 0) -> list[int]:
    """Partial queries each shard answered, from the run's funnel_queries.csv (frames from
    ``first_step`` on: the second half of a run shows the placement the coordinator chose).
    Counted from the query reports, so they do not depend on a shard's counter surviving."""
    counts: Counter[int] = Counter()
    with (run_dir / "funnel_queries.csv").open(encoding="utf-8") as f:
        for row in csv.DictReader(f):
            if int(row["frame"]) < first_step:
                continue
            for item in row["shard_candidates"].split():
                counts[int(item.partition(":")[0].partition("/")[2])] += 1
    return [counts.get(r, 0) for r in range(robots)]


class Pacer:
    """Called after each lock-step step, makes the step last at least ``step_s``: robots whose
    frames come at a rate, as real ones do, while the swarm still answers every step before
    the next (a replay over in a few seconds measures mostly how long the coordinator took to
    see the load)."""

    def __init__(self, step_s: float) -> None:
        self.step_s = step_s
        self._last = time.perf_counter()

    def __call__(self) -> None:
        wait = self._last + self.step_s - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        self._last = time.perf_counter()
