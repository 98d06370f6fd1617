"""Offline evaluation benchmark: wall time of the paper preset's centralized
and 10-robot decentralized scoring, against a baseline measured in the same
run, on the real TUM constellations (../shared/data) and the synthetic world.

    python bench/bench_offline.py --out bench/results/offline.json

The baseline is bench/baseline_naive.py timed on a random sample of pairs and
scaled to the number of pairs scored; ratios (baseline / ours) are what to
compare across machines, the seconds are for this machine only.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline_naive import naive_score

from swarmrec.core.association import build_table, score_pairs
from swarmrec.core.presets import get_preset
from swarmrec.core.types import ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.evaluation.bandwidth import holder_load, paper_byte_model
from swarmrec.evaluation.scoring import score_centralized, score_decentralized

REPO = Path(__file__).resolve().parents[1]
TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"
#: Published figures (REFERENCE_NOTES / the issue), on the authors' kind of machine.
PUBLISHED_SCRIPTS_S = {"centralized": 436.0, "decentralized_10": 22.5}


def _best_of(fn: Any, repeat: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def bench_sequence(name: str, load: Any, repeat: int, sample: int) -> dict[str, Any]:
    preset = get_preset("paper")
    t_load, seq = _best_of(load, 1)
    assert isinstance(seq, ConstellationSequence)
    build_table(seq.constellations[:5], seq.n_labels)  # compile (or load the numba cache) once
    t_prep, table = _best_of(lambda: build_table(seq.constellations, seq.n_labels), repeat)
    t_cen, matrix = _best_of(lambda: score_centralized(seq, preset, table=table), repeat)
    t_dec, run = _best_of(lambda: score_decentralized(seq, 10, preset, table=table), repeat)

    # Same-run baseline on a random sample of the centralized pairs.
    rng = np.random.default_rng(0)
    pick = rng.choice(matrix.scores.shape[0], size=min(sample, matrix.scores.shape[0]), replace=False)
    i, j = matrix.pairs_i[pick], matrix.pairs_j[pick]
    t0 = time.perf_counter()
    naive = [
        naive_score(seq.constellations[a], seq.constellations[b], seq.n_labels)
        for a, b in zip(i, j, strict=True)
    ]
    t_naive = (time.perf_counter() - t0) / len(pick)
    agree = bool(np.allclose(naive, matrix.scores[pick], rtol=0, atol=1e-12))
    t_kernel, _ = _best_of(
        lambda: score_pairs(table, i, j, d=0.25, min_common=3, same_label_only=False), repeat
    )
    n_pairs = int(matrix.scores.shape[0])
    n_dec_pairs = int(run.matrix.scores.shape[0])
    return {
        "frames": len(seq),
        "centralized": {
            "pairs_scored": n_pairs,
            "seconds_scoring": t_cen,
            "seconds_end_to_end": t_load + t_prep + t_cen,
            "naive_baseline_seconds_extrapolated": t_naive * n_pairs,
            "speedup_vs_naive_baseline": t_naive * n_pairs / t_cen,
            "per_pair_us": {"ours": 1e6 * t_kernel / len(pick), "naive": 1e6 * t_naive},
            "naive_agrees_on_sample": agree,
            "sample_pairs": len(pick),
        },
        "decentralized_10": {
            "pairs_scored": n_dec_pairs,
            "seconds_scoring": t_dec,
            "seconds_end_to_end": t_load + t_prep + t_dec,
            "naive_baseline_seconds_extrapolated_for_its_pairs": t_naive * n_dec_pairs,
            "byte_model_per_query": paper_byte_model(run, preset.n_fq).total,
            "balance_ratio": holder_load(run).balance_ratio,
        },
        "seconds_load": t_load,
        "seconds_prepare": t_prep,
        "name": name,
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "offline.json")
    parser.add_argument("--repeat", type=int, default=3, help="best of N timings (default 3)")
    parser.add_argument("--sample", type=int, default=3000, help="pairs timed for the baseline")
    args = parser.parse_args()
    from swarmrec.synthetic import OfficeConfig, generate_office

    results: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": len(__import__("os").sched_getaffinity(0))},
        "published_scripts_seconds": PUBLISHED_SCRIPTS_S,
        "sequences": {},
    }
    if TUM_ZIP.exists():
        results["sequences"]["tum_fr3"] = bench_sequence(
            "tum_fr3", lambda: read_constellations(TUM_ZIP), args.repeat, args.sample
        )
    else:
        print(f"note: {TUM_ZIP} not found, benchmarking the synthetic world only", file=sys.stderr)
    results["sequences"]["synthetic"] = bench_sequence(
        "synthetic", lambda: generate_office(OfficeConfig(seed=0)).sequence, args.repeat, args.sample
    )
    results["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    for key, r in results["sequences"].items():
        c, d = r["centralized"], r["decentralized_10"]
        print(
            f"{key}: centralized {c['seconds_end_to_end']:.2f} s end to end "
            f"({c['speedup_vs_naive_baseline']:.0f}x the same-run naive baseline), "
            f"decentralized x10 {d['seconds_end_to_end']:.2f} s end to end"
        )
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
