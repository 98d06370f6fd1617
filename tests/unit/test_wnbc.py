"""The weighted naive Bayes classifier (Eq. 12-16 of the WNBC paper) on cases worked out by hand."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.fusion.flooding import simulate_flooding
from swarmrec.fusion.street import generate_configurations
from swarmrec.fusion.wnbc import (
    LIKELIHOOD_FLOOR,
    AgreementWeightLaw,
    FusionState,
    LikelihoodError,
    PaperWeightLaw,
    WeightLaw,
    hop_limit,
    hop_weight,
    make_weight_law,
    normalise_likelihood,
    wnbc_update,
    wrap_angle,
    yaw_weight,
)

OWN = [0.5, 0.3, 0.2]
MSG = [0.2, 0.5, 0.3]
# Eq. 12 with P(R) = 1/2 for OWN and MSG, by hand:
#   product 0.10, 0.15, 0.06 (sum 0.31) -> naive Bayes 10/31, 15/31, 6/31
#   1/2 * naive + 1/2 * OWN = 51/124, 243/620, 61/310
HALF_MIX = [51 / 124, 243 / 620, 61 / 310]


def test_update_mixes_naive_bayes_and_the_old_posterior_with_the_weight() -> None:
    assert wnbc_update(OWN, MSG, 0.5) == pytest.approx(HALF_MIX, abs=1e-6)


def test_weight_one_is_the_naive_bayes_update_and_weight_zero_changes_nothing() -> None:
    assert wnbc_update(OWN, MSG, 1.0) == pytest.approx([10 / 31, 15 / 31, 6 / 31], abs=1e-6)
    assert wnbc_update(OWN, MSG, 0.0) == pytest.approx(OWN, abs=1e-12)


def test_update_rejects_a_weight_outside_zero_one() -> None:
    with pytest.raises(ValueError, match="weight"):
        wnbc_update(OWN, MSG, 1.5)


def test_fusion_state_applies_the_paper_weight_of_a_neighbour() -> None:
    # lambda 1, 1 hop, same yaw: P(R) = (1 + 1)^-1 * exp(0) = 1/2.
    state = FusionState(OWN, 0.0, PaperWeightLaw(lam=1.0))
    step = state.incorporate(origin=4, likelihood=MSG, hops=1, yaw=0.0)
    assert step is not None and step.weight == pytest.approx(0.5)
    assert state.posterior == pytest.approx(HALF_MIX, abs=1e-6)
    assert state.decision == 0 and state.incorporated == 1 and state.ignored == 0


def test_hop_weight_is_eq_14() -> None:
    assert hop_weight(0, 2.0) == 1.0
    assert hop_weight(1, 2.0) == pytest.approx(1 / 4)
    assert hop_weight(3, 1.0) == pytest.approx(1 / 4)
    assert hop_weight(5, 0.0) == 1.0


def test_yaw_weight_is_a_gaussian_of_variance_pi_over_3() -> None:
    # exp(-(pi/2)^2 / (2 pi / 3)) = exp(-3 pi / 8)
    assert yaw_weight(math.pi / 2) == pytest.approx(math.exp(-3 * math.pi / 8))
    assert yaw_weight(0.0) == 1.0
    assert yaw_weight(0.3) == yaw_weight(-0.3)


@pytest.mark.parametrize("k", [-3, -1, 0, 1, 2, 5])
def test_wrap_angle_removes_whole_turns(k: int) -> None:
    assert wrap_angle(0.1 + 2 * math.pi * k) == pytest.approx(0.1, abs=1e-12)
    assert wrap_angle(-2.0 + 2 * math.pi * k) == pytest.approx(-2.0, abs=1e-12)


def test_wrap_angle_keeps_half_turns_in_range() -> None:
    for angle in (math.pi, -math.pi, 3 * math.pi, -3 * math.pi):
        assert abs(wrap_angle(angle)) == pytest.approx(math.pi)
        assert -math.pi <= wrap_angle(angle) <= math.pi
    assert wrap_angle(7 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_yaws_either_side_of_the_half_turn_are_close() -> None:
    # Yaws 3.0 and -3.0 rad are 2 pi - 6 = 0.283 rad apart, not 6.
    state = FusionState(OWN, 3.0, PaperWeightLaw(lam=0.0))
    step = state.incorporate(origin=1, likelihood=MSG, hops=1, yaw=-3.0)
    assert step is not None
    assert step.weight == pytest.approx(math.exp(-((2 * math.pi - 6.0) ** 2) / (2 * math.pi / 3)))
    assert step.weight > 0.95
    # Opposite yaws weigh exp(-pi^2 / (2 pi / 3)) = exp(-3 pi / 2) whichever way round.
    assert yaw_weight(math.pi) == pytest.approx(math.exp(-3 * math.pi / 2))
    assert yaw_weight(-math.pi) == pytest.approx(yaw_weight(math.pi))


def test_lambda_zero_with_equal_yaws_is_the_unweighted_naive_bayes() -> None:
    # OWN x [0.2, 0.5, 0.3] x [0.6, 0.2, 0.2] = [0.06, 0.03, 0.012] -> [10, 5, 2] / 17,
    # whatever the hop counts.
    state = FusionState(OWN, 1.0, make_weight_law("paper", lam=0.0))
    state.incorporate(1, MSG, hops=4, yaw=1.0)
    state.incorporate(2, [0.6, 0.2, 0.2], hops=7, yaw=1.0)
    assert state.posterior == pytest.approx([10 / 17, 5 / 17, 2 / 17], abs=1e-6)


def test_huge_lambda_ignores_everything_beyond_hop_zero() -> None:
    state = FusionState(OWN, 0.0, PaperWeightLaw(lam=100.0))
    for origin in range(1, 10):
        state.incorporate(origin, [0.001, 0.001, 0.998], hops=1, yaw=0.0)
    assert state.incorporated == 9
    assert state.posterior == pytest.approx(OWN, abs=1e-12)
    assert state.decision == 0


def test_messages_beyond_r_max_are_ignored_and_counted() -> None:
    state = FusionState(OWN, 0.0, PaperWeightLaw(lam=1.0), r_max=2)
    assert state.incorporate(1, MSG, hops=2, yaw=0.0) is not None
    assert state.incorporate(2, MSG, hops=3, yaw=0.0) is None
    assert state.incorporated == 1 and state.ignored == 1
    assert state.ignored_reasons["beyond r_max"] == 1


def test_a_second_message_of_the_same_origin_or_the_own_is_ignored() -> None:
    state = FusionState(OWN, 0.0, PaperWeightLaw(lam=1.0), own_id=0)
    state.incorporate(3, MSG, hops=1, yaw=0.0)
    after_one = state.posterior
    assert state.incorporate(3, [0.9, 0.05, 0.05], hops=2, yaw=0.0) is None
    assert state.incorporate(0, [0.9, 0.05, 0.05], hops=2, yaw=0.0) is None
    assert np.array_equal(state.posterior, after_one)
    assert state.ignored_reasons == {"duplicate origin": 1, "own message": 1}


def test_state_keeps_the_posterior_after_each_message() -> None:
    state = FusionState(OWN, 0.0, PaperWeightLaw(lam=1.0))
    state.incorporate(1, MSG, hops=1, yaw=0.0)
    state.incorporate(2, [0.05, 0.05, 0.9], hops=1, yaw=0.0)
    assert state.posterior_after(0) == pytest.approx(OWN)
    assert state.posterior_after(1) == pytest.approx(HALF_MIX, abs=1e-6)
    assert np.array_equal(state.posterior_after(2), state.posterior)
    assert [state.decision_after(k) for k in range(3)] == [0, 0, state.decision]
    assert [h.origin for h in state.history] == [1, 2]
    with pytest.raises(IndexError):
        state.posterior_after(3)


def test_the_own_output_is_normalised_as_the_paper_divides_grades_by_their_sum() -> None:
    state = FusionState([2.0, 1.0, 1.0], 0.0, PaperWeightLaw())
    assert state.posterior == pytest.approx([0.5, 0.25, 0.25])


def test_zero_probabilities_are_floored_so_no_class_is_vetoed() -> None:
    # Floored (a, b, b) and (b, a, b) with a = 1, b = 1e-6: the product (ab, ab, b^2)
    # normalises to (1, 1, 1e-6) / (2 + 1e-6).
    posterior = wnbc_update(normalise_likelihood([1.0, 0.0, 0.0], 3), [0.0, 1.0, 0.0], 1.0)
    b = LIKELIHOOD_FLOOR
    assert posterior == pytest.approx([1 / (2 + b), 1 / (2 + b), b / (2 + b)], rel=1e-6)


def test_many_confident_messages_neither_underflow_nor_lose_normalisation() -> None:
    state = FusionState([0.4, 0.3, 0.3], 0.0, PaperWeightLaw(lam=0.0))
    for origin in range(1, 501):
        state.incorporate(origin, [0.999, 0.0005, 0.0005], hops=1, yaw=0.0)
    assert np.all(np.isfinite(state.log_posterior))
    assert state.posterior.sum() == pytest.approx(1.0)
    assert state.decision == 0


@pytest.mark.parametrize(
    "bad",
    [[0.5, 0.5], [0.5, float("nan"), 0.5], [0.5, -0.1, 0.6], [0.0, 0.0, 0.0], ["a", "b", "c"]],
)
def test_invalid_likelihoods_raise_a_likelihood_error(bad: list[object]) -> None:
    state = FusionState(OWN, 0.0, PaperWeightLaw())
    with pytest.raises(LikelihoodError):
        state.incorporate(1, bad, hops=1, yaw=0.0)
    assert state.incorporated == 0


def test_agreement_law_is_the_exact_posterior_of_the_mixture_model() -> None:
    # Prior w = 1/2 (lambda 1, 1 hop). Same landmark: p(z|O) = MSG; another landmark:
    # p(z) = mean(MSG) = 1/3 for every class. Posterior = OWN * (w MSG + (1 - w) / 3):
    #   [0.5 (0.1 + 1/6), 0.3 (0.25 + 1/6), 0.2 (0.15 + 1/6)] = [40, 37.5, 19] / 300 -> [80, 75, 38] / 193
    expected = [80 / 193, 75 / 193, 38 / 193]
    state = FusionState(OWN, 0.0, AgreementWeightLaw(PaperWeightLaw(lam=1.0)))
    step = state.incorporate(1, MSG, hops=1, yaw=0.0)
    assert state.posterior == pytest.approx(expected, abs=1e-6)
    # Its weight: w a / (w a + (1 - w) u) with a = <OWN, MSG> = 0.31, u = 1/3.
    assert step is not None and step.weight == pytest.approx(0.31 / (0.31 + 1 / 3))


def test_agreement_law_trusts_agreeing_messages_more_than_contradicting_ones() -> None:
    law = AgreementWeightLaw(PaperWeightLaw(lam=1.0))
    posterior = np.array([0.9, 0.05, 0.05])

    def weight(likelihood: list[float]) -> float:
        return law.weight(
            hops=1, yaw_difference=0.0, likelihood=np.array(likelihood), posterior=posterior, incorporated=0
        )

    assert weight([0.1, 0.8, 0.1]) < 0.5 < weight([0.8, 0.1, 0.1])


def test_agreement_law_keeps_certain_priors() -> None:
    posterior, likelihood = np.array([0.9, 0.05, 0.05]), np.array([0.05, 0.05, 0.9])

    def weight(lam: float) -> float:
        law = AgreementWeightLaw(PaperWeightLaw(lam=lam))
        return law.weight(
            hops=2, yaw_difference=0.0, likelihood=likelihood, posterior=posterior, incorporated=3
        )

    assert weight(0.0) == 1.0
    assert weight(100.0) < 1e-40


def test_hop_limit_is_the_last_hop_weighing_at_least_the_tolerance() -> None:
    assert hop_limit(1.0, 0.2) == 4  # 1/5 >= 0.2 > 1/6
    assert hop_limit(2.0, 0.25) == 1  # exactly 1/4 at one hop
    assert hop_limit(2.0, 0.2) == 1  # 1/4 >= 0.2 > 1/9
    assert hop_limit(0.0, 0.1) is None


def test_make_weight_law_knows_paper_and_agreement_and_nothing_else() -> None:
    assert make_weight_law("paper", lam=1.0) == PaperWeightLaw(lam=1.0)
    assert make_weight_law("agreement").name == "agreement"
    with pytest.raises(ConfigError, match="paper"):
        make_weight_law("magic")
    with pytest.raises(ConfigError):
        PaperWeightLaw(lam=-1.0)


def recognition_rates(laws: dict[str, WeightLaw], n_messages: int = 9) -> dict[str, np.ndarray]:
    """Correct-decision rate after 0..n_messages incorporated messages (the paper's Fig. 3)
    for each law on the 118 street configurations, each robot's classifier simulated as a
    softmax of Gaussian logits that is right about 86 % of the time."""
    rng = np.random.default_rng(5)
    correct = {name: np.zeros(n_messages + 1) for name in laws}
    for config in generate_configurations(118, seed=0):
        logits = 3.0 * rng.normal(0.0, 1.0, (config.n_robots, 19))
        logits[np.arange(config.n_robots), config.landmarks] += 9.0
        probs = np.exp(logits - logits.max(axis=1, keepdims=True))
        probs /= probs.sum(axis=1, keepdims=True)
        flood = simulate_flooding(config.adjacency, probs, config.yaws)
        for robot, (name, law) in itertools.product(range(config.n_robots), laws.items()):
            state = FusionState(probs[robot], float(config.yaws[robot]), law, own_id=robot)
            for heard in flood.heard[robot]:
                state.incorporate(heard.origin, heard.likelihood, heard.hops, heard.yaw)
            for k in range(n_messages + 1):
                correct[name][k] += state.decision_after(k) == config.landmarks[robot]
    return {name: c / 1180 for name, c in correct.items()}


def test_in_the_street_simulation_the_agreement_law_stays_above_90_percent() -> None:
    rates = recognition_rates(
        {
            "agreement": make_weight_law("agreement"),
            "lambda 0": PaperWeightLaw(lam=0.0),
            "lambda 1": PaperWeightLaw(lam=1.0),
        }
    )
    agreement, unweighted, paper_1 = rates["agreement"], rates["lambda 0"], rates["lambda 1"]
    assert 0.8 < agreement[0] == unweighted[0] < 0.9  # the single robot
    assert np.all(agreement[1:] >= 0.9)
    # The paper's laws lose what they gained once the other clusters' messages arrive.
    assert unweighted[-1] < 0.75 and paper_1[-1] < 0.87
    assert agreement[-1] > paper_1[-1] + 0.1


def test_the_fusion_package_exports_what_its_all_names() -> None:
    import swarmrec.fusion as fusion

    assert sorted(fusion.__all__) == sorted(set(fusion.__all__))
    assert all(hasattr(fusion, name) for name in fusion.__all__)
