"""The report's offline evaluation (:class:`OfflineEvaluation`): computed on a thread while
the swarm stops, it gives what computing it in the report gives, and says when it failed."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.core.presets import get_preset
from swarmrec.core.ranges import label_bounds
from swarmrec.core.types import Trajectory
from swarmrec.evaluation.groundtruth import ground_truth
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.experiments.places.report import OfflineEvaluation
from tests.unit.test_offline_scoring import N_LABELS, _random_sequence

PRESET = get_preset("paper").with_(exclusion=3)
ROBOTS = 3


def _evaluation(seed: int) -> OfflineEvaluation:
    seq = _random_sequence(36, seed)
    n = len(seq)
    # A camera walking a line and back, so that frames far apart in time meet again.
    x = np.r_[np.linspace(0, 5, n // 2), np.linspace(5, 0, n - n // 2)]
    trajectory = Trajectory(
        seq.timestamps.copy(), np.c_[x, np.zeros(n), np.zeros(n)], np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    )
    bounds = label_bounds(PRESET.ranges, N_LABELS, ROBOTS)
    return OfflineEvaluation(seq, as_on_the_wire(seq), trajectory, PRESET, bounds, ROBOTS)


def test_started_on_a_thread_it_gives_what_the_scripts_evaluation_gives() -> None:
    seed = 0  # a sequence where millimetres change a score (most random ones change none)
    started = _evaluation(seed).start(check_offline=True)
    e = _evaluation(seed)  # the reference: each part computed from scratch
    for wire, seq in ((True, e.wire_seq), (False, e.seq)):
        got = started.matrix(wire=wire)
        ref = score_decentralized(seq, ROBOTS, PRESET, bounds=e.bounds).matrix
        assert np.array_equal(got.pairs_i, ref.pairs_i) and np.array_equal(got.pairs_j, ref.pairs_j)
        assert got.scores.tobytes() == ref.scores.tobytes()
    assert e.trajectory is not None
    truth = started.ground_truth()
    assert truth is not None
    ref_truth = ground_truth(e.wire_seq, e.trajectory, exclusion=PRESET.exclusion)
    assert np.array_equal(truth.closures, ref_truth.closures) and truth.closures.any()
    # The millimetres changed some score: the exact evaluation is not the wire's by accident.
    assert started.matrix(wire=False).scores.tobytes() != started.matrix(wire=True).scores.tobytes()


def test_a_failure_on_the_thread_is_raised_where_the_report_asks() -> None:
    e = _evaluation(0)
    e.bounds = np.array([0, 5, 3, N_LABELS])  # not increasing: the evaluation refuses them
    e.start(check_offline=True)
    with pytest.raises(ValueError):
        e.matrix(wire=True)
