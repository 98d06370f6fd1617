"""The compiled data plane breaks ties as numpy does (dataplane/src/argsort.rs).

The published scripts keep the first entries of numpy's default, unstable argsort, so
a compiled shard or querier keeps the offline evaluation's candidates only if it runs
numpy's very sort. numpy 2.4.6 picks one of three programs per process (x86-simd-sort
for X86_V4 or X86_V3, or its own introsort) from the CPU and NPY_DISABLE_CPU_FEATURES /
NPY_ENABLE_CPU_FEATURES; each choice is checked here by running numpy in a process with
those variables and the compiled code (``swarmrec-dataplane compute``) with the same, on
random arrays built to tie (few distinct values, negated zeros, sorted and reversed runs,
sizes either side of x86-simd-sort's 256-element networks). The answers are numpy's, read
from numpy; nothing is recomputed here.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.core.selection import select_candidates, select_robots
from tests.integration.support import compute

ROOT = Path(__file__).resolve().parents[2]

#: numpy's answers to the cases, computed in a process of its own (the variables are
#: read once, when numpy is imported).
NUMPY_SIDE = r"""
import json, sys
import numpy as np
from numpy._core._multiarray_umath import __cpu_features__ as features
from swarmrec.core.selection import select_candidates, select_robots
cases = json.load(open(sys.argv[1]))
out = []
for case in cases:
    if case["op"] == "argsort":
        dtype = np.float64 if case["dtype"] == "f64" else np.int64
        out.append(np.argsort(np.array(case["values"], dtype=dtype)).tolist())
    elif case["op"] == "select_candidates":
        out.append(select_candidates(np.array(case["scores"]), case["n_ret"]).tolist())
    else:
        out.append(select_robots(case["robots"], case["n_fq"], case["self_robot"]).tolist())
v3, v4 = features["X86_V3"], features["X86_V4"]
level = "X86_V4" if v3 and v4 else "X86_V3" if v3 else "baseline"
print(json.dumps({"level": level, "answers": out}))
"""

#: The three programs, each chosen by the variables numpy reads (on a CPU that has
#: AVX-512: the machines this project runs on; a CPU without it checks fewer).
CHOICES = {
    "default": {},
    "no X86_V4": {"NPY_DISABLE_CPU_FEATURES": "X86_V4"},
    "no X86_V3": {"NPY_DISABLE_CPU_FEATURES": "X86_V3"},
    "only X86_V3": {"NPY_ENABLE_CPU_FEATURES": "X86_V3"},
}


def numpy_env(choice: dict[str, str]) -> dict[str, str]:
    """This process's environment with numpy's CPU-feature variables as ``choice`` sets them."""
    return {k: v for k, v in os.environ.items() if not k.startswith("NPY_")} | choice


def tied_values(rng: random.Random, n: int) -> list[float]:
    """Negated partial scores as the selection sorts them: few distinct fractions, many zeros."""
    shape = rng.choice(["few", "zeros", "sorted", "reversed", "equal", "wide"])
    if shape == "equal":
        return [-0.5] * n
    if shape == "wide":
        return [-rng.random() for _ in range(n)]
    distinct = [0.0] + [-(k / rng.randint(2, 9)) for k in range(1, rng.randint(2, 6))]
    weights = [rng.random() * (8 if shape == "zeros" and i == 0 else 1) for i in range(len(distinct))]
    values = rng.choices(distinct, weights, k=n)
    if shape == "sorted":
        values.sort()
    elif shape == "reversed":
        values.sort(reverse=True)
    return [-0.0 if v == 0.0 else v for v in values]


def cases(seed: int) -> list[dict[str, Any]]:
    rng = random.Random(seed)
    sizes = [2, 3, 7, 8, 9, 15, 16, 17, 31, 64, 100, 128, 255, 256, 257, 300, 512, 1000, 2585, 4096, 7000]
    out: list[dict[str, Any]] = []
    for n in sizes:
        for _ in range(6):
            out.append({"op": "argsort", "dtype": "f64", "values": tied_values(rng, n)})
            counts = [-rng.randint(0, rng.randint(1, 6)) for _ in range(n)]
            out.append({"op": "argsort", "dtype": "i64", "values": counts})
    for _ in range(150):
        n = rng.choice([10, 40, 300, 2585, 5000])
        scores = [-v for v in tied_values(rng, n)]
        out.append({"op": "select_candidates", "scores": scores, "n_ret": rng.choice([1, 3, 10, 25])})
    for _ in range(150):
        robots = [rng.randrange(rng.randint(1, 12)) for _ in range(rng.randint(0, 40))]
        self_robot = rng.choice([None, rng.randrange(12)])
        n_fq = rng.randint(1, 5)
        out.append({"op": "select_robots", "robots": robots, "n_fq": n_fq, "self_robot": self_robot})
    return out


@pytest.mark.parametrize("choice", list(CHOICES))
def test_compiled_sorts_and_selections_equal_numpys(choice: str, tmp_path: Path) -> None:
    env = numpy_env(CHOICES[choice])
    requests = cases(seed=len(choice))
    (tmp_path / "cases.json").write_text(json.dumps(requests))
    done = subprocess.run(
        [sys.executable, "-c", NUMPY_SIDE, str(tmp_path / "cases.json")],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=300,
        check=True,
    )
    numpy_side = json.loads(done.stdout)
    assert compute([{"op": "level"}], env) == [numpy_side["level"]]
    answers = compute(requests, env)
    mismatched = [
        (i, r["op"], len(r.get("values", r.get("scores", []))))
        for i, (r, a, b) in enumerate(zip(requests, answers, numpy_side["answers"], strict=True))
        if a != b
    ]
    assert not mismatched, f"{len(mismatched)} of {len(requests)} differ from numpy: {mismatched[:10]}"


def test_every_level_is_checked_on_this_machine() -> None:
    """The choices above reach all three programs here (else a level went untested)."""
    levels = set()
    for extra in CHOICES.values():
        env = numpy_env(extra)
        levels.update(compute([{"op": "level"}], env))
    assert levels == {"X86_V4", "X86_V3", "baseline"}


def test_ties_really_straddle_the_cuts_checked() -> None:
    """The selection cases exercise numpy's tie-break: in most of them equal scores
    straddle the n_ret cut and an unstable sort decides (else the test proves little)."""
    straddling = 0
    requests = [r for r in cases(seed=1) if r["op"] == "select_candidates"]
    for r in requests:
        scores = np.array(r["scores"])
        positive = np.sort(scores[scores > 0])[::-1]
        n_ret = r["n_ret"]
        if positive.shape[0] > n_ret and positive[n_ret - 1] == positive[n_ret]:
            straddling += 1
    assert straddling > len(requests) // 2


def test_vendored_sort_is_the_installed_numpys() -> None:
    """The vendored x86-simd-sort came from the numpy the project pins and runs."""
    vendored = (ROOT / "dataplane" / "vendor" / "NUMPY_VERSION").read_text().strip()
    pinned = [
        line.split("==")[1].strip()
        for line in (ROOT / "requirements.lock").read_text().splitlines()
        if line.startswith("numpy==")
    ]
    assert pinned == [vendored], "refresh dataplane/vendor (dataplane/vendor/README.md) to the pinned numpy"
    assert np.__version__ == vendored


def test_python_reference_still_agrees_with_numpy_on_a_known_case() -> None:
    """The Python selection is what the compiled one is compared with: a hand-checked case."""
    assert select_candidates(np.array([0.0, 0.5, 0.5, 0.25]), 5).tolist() == [1, 2, 3]
    assert select_robots([2, 2, 0], 1, 4).tolist() == [2, 4]
