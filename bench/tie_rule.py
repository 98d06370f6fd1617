"""Which tie rule the published scores depend on (docs/dataplane.md, "A tie rule").

Where equal scores straddle a cut (a range holder's ``n_ret`` candidates, a querier's
``n_fq`` robots), the published scripts, and swarmrec after them, let numpy's default
(unstable) ``argsort`` decide. A compiled shard or querier cannot call numpy, so it needs
a rule it can state. This measures, on the real TUM constellations and the paper preset,
how often such ties happen, how often numpy's pick differs from a stated rule (lowest
slot first, highest slot first), and how many rows of the published score matrices
(tests/fixtures) each rule changes when the offline evaluation uses it.

    .venv/bin/python bench/tie_rule.py --out bench/results/tie_rule.json
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import swarmrec.evaluation.scoring as scoring  # noqa: E402
from swarmrec.core import selection  # noqa: E402
from swarmrec.core.association import build_table  # noqa: E402
from swarmrec.core.presets import get_preset  # noqa: E402
from swarmrec.datasets.constellations import read_constellations  # noqa: E402
from tests.published import rows_differing  # noqa: E402

TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"
ROBOTS = (3, 4, 10, 20)
#: numpy: the published behaviour; low/high: keep the lowest/highest slot (robot) of a tie.
RULES = ("numpy", "low", "high")

IntArray = npt.NDArray[np.int64]


def by_rule(scores: npt.NDArray[Any], keep: int, rule: str) -> IntArray:
    """The ``keep`` best of the positive ``scores``, ties at the cut by slot order (``rule``)."""
    positive = np.flatnonzero(scores > 0)
    sign = 1 if rule == "low" else -1
    order = sorted(positive.tolist(), key=lambda i: (-scores[i], sign * i))
    return np.sort(np.array(order[:keep], np.int64))


def straddles(scores: npt.NDArray[Any], keep: int) -> bool:
    """Whether equal positive scores straddle the ``keep`` cut."""
    positive = np.sort(scores[scores > 0])[::-1]
    return positive.shape[0] > keep and positive[keep - 1] == positive[keep]


class Counting:
    """The selection functions the offline evaluation calls, counting ties and applying ``rule``."""

    def __init__(self, rule: str) -> None:
        self.rule = rule
        self.counts = dict.fromkeys(
            ("candidate_cuts", "candidate_ties", "candidate_numpy_differs", "robot_cuts", "robot_ties",
             "robot_numpy_differs"),
            0,
        )  # fmt: skip

    def candidates(self, values: npt.NDArray[Any], n_ret: int) -> list[IntArray]:
        out = selection.select_candidates_many(values, n_ret)
        for b, row in enumerate(np.asarray(values)):
            self.counts["candidate_cuts"] += 1
            if not straddles(row, n_ret):
                continue
            self.counts["candidate_ties"] += 1
            stated = by_rule(row, n_ret, "low")
            self.counts["candidate_numpy_differs"] += not np.array_equal(stated, np.sort(out[b]))
            if self.rule != "numpy":
                out[b] = by_rule(row, n_ret, self.rule)
        return out

    def robots(self, cand: npt.ArrayLike, n_fq: int, self_robot: int | None) -> IntArray:
        out = selection.select_robots(cand, n_fq, self_robot)
        robots = np.asarray(cand, np.int64)
        self.counts["robot_cuts"] += 1
        if robots.shape[0] == 0:
            return out
        # Robots with no candidate may fill the list too (as in the scripts): zeros count.
        counts = np.bincount(robots)
        ranked = np.sort(counts)[::-1]
        if not (ranked.shape[0] > n_fq and ranked[n_fq - 1] == ranked[n_fq]):
            return out
        self.counts["robot_ties"] += 1
        extra = [self_robot] if self_robot is not None else []

        def stated(rule: str) -> IntArray:
            sign = 1 if rule == "low" else -1
            order = sorted(range(counts.shape[0]), key=lambda r: (-counts[r], sign * r))
            return np.unique(np.array(order[:n_fq] + extra, np.int64))

        self.counts["robot_numpy_differs"] += not np.array_equal(stated("low"), out)
        return out if self.rule == "numpy" else stated(self.rule)


def measure(rule: str, seq: Any, table: Any, robots: int) -> dict[str, int]:
    counting = Counting(rule)
    patched: dict[str, Callable[..., Any]] = {
        "select_candidates_many": counting.candidates,
        "select_robots": counting.robots,
    }
    saved = {name: getattr(scoring, name) for name in patched}
    try:
        for name, fn in patched.items():
            setattr(scoring, name, fn)
        run = scoring.score_decentralized(seq, robots, get_preset("paper"), table=table)
    finally:
        for name, fn in saved.items():
            setattr(scoring, name, fn)
    return counting.counts | {
        "published_rows": int(run.matrix.dense().shape[0]),
        "published_rows_differing": len(rows_differing(f"decentralized_{robots}", run.matrix.dense())),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "tie_rule.json")
    args = ap.parse_args()
    seq = read_constellations(TUM_ZIP)
    table = build_table(seq.constellations, seq.n_labels)
    results: dict[str, dict[str, dict[str, int]]] = {}
    for rule in RULES:
        results[rule] = {str(r): measure(rule, seq, table, r) for r in ROBOTS}
        row = ", ".join(f"{r} robots {v['published_rows_differing']}" for r, v in results[rule].items())
        print(f"{rule:6s} published rows differing: {row}")
    out = {
        "dataset": TUM_ZIP.name,
        "preset": "paper",
        "numpy": np.__version__,
        "cpu_simd": _simd_found(),
        "rules": results,
        "about": (
            "candidate_ties: candidate selections (one query's slice on one range holder) where "
            "equal scores straddle the n_ret cut; candidate_numpy_differs: of those, where numpy's "
            "pick is not 'lowest slot first'; robot_*: the same for the n_fq robots; "
            "published_rows_differing: rows of the published decentralized matrix that change when "
            "the offline evaluation breaks those ties by the rule instead of numpy's argsort"
        ),
    }
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")


def _simd_found() -> list[str]:
    """The SIMD extensions numpy found on this machine (its argsort dispatches on them)."""
    from numpy._core._multiarray_umath import __cpu_features__  # type: ignore[attr-defined]

    return sorted(k for k, v in __cpu_features__.items() if v and k.startswith("AVX512"))


if __name__ == "__main__":
    main()
