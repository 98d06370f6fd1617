"""The landmark simulation's own logic, without processes: laws and settings, the
delivery count that ends a round, the check against the core, the rates, the confusion
matrix and the figures (the run over real processes is tests/integration/test_landmark_simulation.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.experiments.landmarks.report import confusion_matrix, plot_configuration, recognition_rates
from swarmrec.experiments.landmarks.simulation import (
    DEFAULT_LAWS,
    VIEW_PRESETS,
    LandmarkSettings,
    LawChoice,
    RobotRound,
    check_against_core,
    expected_deliveries,
    parse_law,
    render_views,
)
from swarmrec.fusion import FusionState, PaperWeightLaw, generate_configuration, make_weight_law
from swarmrec.fusion.street import SwarmConfiguration


def test_laws_parse_from_the_command_line_form() -> None:
    assert parse_law("paper:1") == LawChoice("paper", 1.0)
    assert parse_law(" agreement ") == LawChoice("agreement", None)
    assert parse_law("paper").law() == PaperWeightLaw(lam=2.0)
    assert [law.key for law in DEFAULT_LAWS] == ["paper:0", "paper:1", "paper:2", "paper:100", "agreement"]
    for bad, match in [
        ("magic:1", "unknown weight law"),
        ("paper:x", "not a number"),
        ("paper:-2", "lambda"),
    ]:
        with pytest.raises(ConfigError, match=match):
            parse_law(bad)


def test_a_law_goes_on_the_wire_with_its_lambda_only_when_given() -> None:
    assert LawChoice("paper", 100.0).to_proto().HasField("lambda")
    assert getattr(LawChoice("paper", 100.0).to_proto(), "lambda") == 100.0
    assert not LawChoice("agreement").to_proto().HasField("lambda")


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"configurations": 0}, "configurations"),
        ({"robots": 1}, "robots"),
        ({"laws": ()}, "at least one"),
        ({"laws": (LawChoice("paper", 1.0), LawChoice("paper", 1.0))}, "repeat"),
        ({"views": "foggy"}, "views"),
        ({"radio_range": 0.0}, "radio_range"),
    ],
)
def test_bad_simulation_settings_are_refused_before_anything_starts(
    tmp_path: Path, changes: dict[str, object], match: str
) -> None:
    with pytest.raises(ConfigError, match=match):
        LandmarkSettings(out=tmp_path, **changes)  # type: ignore[arg-type]


def line_configuration(n: int) -> SwarmConfiguration:
    """A real configuration's fields with its graph replaced by the line 0-1-...-(n-1)."""
    c = generate_configuration(0, seed=0)
    adj = np.zeros((n, n), bool)
    for i in range(n - 1):
        adj[i, i + 1] = adj[i + 1, i] = True
    return SwarmConfiguration(
        index=0,
        positions=c.positions[:n],
        yaws=c.yaws[:n],
        landmarks=c.landmarks[:n],
        distances=c.distances[:n],
        view_angles=c.view_angles[:n],
        offsets=c.offsets[:n],
        clusters=c.clusters[:n],
        cluster_landmarks=c.cluster_landmarks,
        formations=c.formations,
        adjacency=adj,
    )


def test_a_round_delivers_n_copies_per_neighbour_to_each_robot() -> None:
    # Each neighbour broadcasts its own output and forwards every other origin once:
    # n copies from each neighbour, so n on the line's ends and 2n inside.
    assert expected_deliveries(line_configuration(5)) == [5, 10, 10, 10, 5]
    c = generate_configuration(3, seed=0)
    assert expected_deliveries(c) == [c.n_robots * int(c.adjacency[i].sum()) for i in range(c.n_robots)]


def record_from_core(robot: int, probs: np.ndarray, yaws: np.ndarray, law: PaperWeightLaw) -> RobotRound:
    """A robot's record as the services would report it, hearing the others in id order."""
    state = FusionState(probs[robot], float(yaws[robot]), law, own_id=robot)
    decisions = [state.decision]
    history = []
    for origin in range(len(probs)):
        if origin != robot:
            step = state.incorporate(origin, probs[origin], 1 + abs(origin - robot), float(yaws[origin]))
            decisions.append(state.decision)
            history.append((origin, 1 + abs(origin - robot), float(yaws[origin]), step.weight))
    return RobotRound(
        configuration=0,
        law="paper:1",
        robot=robot,
        truth=0,
        probabilities=probs[robot].tolist(),
        decisions=decisions,
        history=history,
        posterior=state.posterior.tolist(),
        duplicates=0,
        rejected=0,
        expected_deliveries=0,
        complete=True,
    )


def test_the_check_against_the_core_finds_agreement_a_changed_decision_and_a_lost_vector() -> None:
    rng = np.random.default_rng(3)
    probs = rng.dirichlet(np.full(19, 0.3), size=4)
    yaws = rng.uniform(-1, 1, 4)
    law = PaperWeightLaw(lam=1.0)
    record = record_from_core(1, probs, yaws, law)
    vectors = [p.tolist() for p in probs]
    assert check_against_core(record, vectors, yaws.tolist(), law) == 0.0
    # The same record judged under another law no longer matches.
    other = check_against_core(record, vectors, yaws.tolist(), PaperWeightLaw(lam=0.0))
    assert other is not None and other > 1e-6
    wrong = record_from_core(1, probs, yaws, law)
    wrong.decisions[2] = (wrong.decisions[2] + 1) % 19
    assert check_against_core(wrong, vectors, yaws.tolist(), law) == math.inf
    vectors[3] = None  # type: ignore[call-overload]
    assert check_against_core(record, vectors, yaws.tolist(), law) is None


def rr(law: str, truth: int, decisions: list[int]) -> RobotRound:
    return RobotRound(
        0, law, 0, truth, [], decisions, [(1, 1, 0.0, 1.0)] * (len(decisions) - 1), [], 0, 0, 0, True
    )


def test_rates_count_each_robot_at_every_k_it_reached_and_only_its_own_law() -> None:
    rounds = [
        rr("a", 2, [2, 2, 5]),  # right, right, wrong
        rr("a", 4, [1, 4, 4]),  # wrong, right, right
        rr("a", 0, [0]),  # heard nobody: counts at k = 0 only
        rr("b", 0, [1, 1, 1]),
    ]
    rate, count = recognition_rates(rounds, "a", 3)
    assert count.tolist() == [3, 2, 2, 0]
    np.testing.assert_allclose(rate[:3], [2 / 3, 1.0, 0.5])
    assert math.isnan(rate[3])


def test_the_confusion_matrix_counts_true_against_decided_after_k_or_after_all() -> None:
    rounds = [rr("a", 2, [2, 5]), rr("a", 2, [2, 2]), rr("a", 7, [3]), rr("b", 1, [1, 1])]
    after_all = confusion_matrix(rounds, "a")
    assert after_all.sum() == 3 and after_all[2, 5] == 1 and after_all[2, 2] == 1 and after_all[7, 3] == 1
    first = confusion_matrix(rounds, "a", k=1)
    assert first.sum() == 2 and first[2, 5] == 1 and first[2, 2] == 1


def test_views_are_rendered_per_robot_from_their_own_stream(tmp_path: Path) -> None:
    configs = [generate_configuration(i, seed=0) for i in range(2)]
    views = render_views(configs, 0, VIEW_PRESETS["nominal"])
    again = render_views(configs[1:], 0, VIEW_PRESETS["nominal"])
    assert views[0].shape == (10, 64, 64, 3) and views[0].dtype == np.uint8
    np.testing.assert_array_equal(views[1], again[0])  # independent of what else is rendered
    harsh = render_views(configs[:1], 0, VIEW_PRESETS["harsh"])
    assert not np.array_equal(harsh[0], views[0])


def test_a_configuration_picture_is_drawn(tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    c = generate_configuration(5, seed=0)
    fig, ax = plt.subplots()
    plot_configuration(ax, c, c.landmarks.tolist(), title="t")
    fig.savefig(tmp_path / "c.png")
    plt.close(fig)
    assert (tmp_path / "c.png").stat().st_size > 1000
    assert len(ax.patches) == c.n_robots  # one triangle per robot


def test_the_agreement_law_prior_default_is_lambda_one() -> None:
    assert LawChoice("agreement").law() == make_weight_law("agreement", lam=1.0)
