"""The fusion robot's pure logic (swarmrec.fusion.robot), without a bus: early-message buffering, the
neighbour check, round rules, the wire conversion, the fusion settings, and a whole
flood on an emulated bus that delivers in any order."""

from __future__ import annotations

import math
import random
from collections import deque

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.fusion import FloodMessage, FusionState, make_weight_law, simulate_flooding
from swarmrec.fusion.robot import (
    KEPT_ROUNDS,
    Broadcast,
    EarlyBuffer,
    FusionRobot,
    Handled,
    Handling,
    RoundError,
)
from swarmrec.runtime.settings import load_config
from swarmrec.services.settings import FusionSettings, LandmarkSettings
from swarmrec.wire.fusion import classifier_output_to_flood, flood_to_classifier_output, weight_law_from_proto

N_CLASSES = 5
UNIFORM = [1 / N_CLASSES] * N_CLASSES


def robot(i: int, n: int, *, r_max: int | None = None, early: int = 16) -> FusionRobot:
    return FusionRobot(
        i, n, law=make_weight_law("paper", lam=1.0), n_classes=N_CLASSES, r_max=r_max, early_per_round=early
    )


def msg(round_id: int, origin: int, sender: int, hops: int, likelihood: object = UNIFORM) -> FloodMessage:
    return FloodMessage(round_id, origin, sender, hops, 0.0, likelihood)  # type: ignore[arg-type]


def probabilities(rng: np.random.Generator) -> np.ndarray:
    """A float32 probability vector, as the wire carries it."""
    v = rng.dirichlet(np.ones(N_CLASSES)).astype(np.float32)
    return v.astype(np.float64)


def line(n: int) -> list[list[int]]:
    return [[j for j in (i - 1, i + 1) if 0 <= j < n] for i in range(n)]


# --- the early-message buffer -------------------------------------------------------


def test_the_early_buffer_keeps_at_most_per_round_messages_of_a_round() -> None:
    buf = EarlyBuffer(per_round=2)
    assert buf.add(msg(1, 0, 0, 0)) == (True, 0)
    assert buf.add(msg(1, 2, 2, 0)) == (True, 0)
    assert buf.add(msg(1, 3, 3, 0)) == (False, 0)
    assert len(buf) == 2


def test_a_lower_new_round_evicts_the_highest_buffered_round_when_every_slot_is_taken() -> None:
    buf = EarlyBuffer(per_round=4, max_rounds=2)
    buf.add(msg(5, 0, 0, 0))
    buf.add(msg(1_000_000, 0, 0, 0))  # a bogus far round takes a slot
    buf.add(msg(1_000_000, 1, 1, 0))
    assert buf.add(msg(6, 0, 0, 0)) == (True, 2)
    assert buf.rounds() == [5, 6]
    assert buf.add(msg(7, 0, 0, 0)) == (False, 0)  # higher than everything kept: refused


def test_taking_a_round_returns_its_messages_in_arrival_order_and_drops_lower_rounds() -> None:
    buf = EarlyBuffer(per_round=8)
    first, second = msg(3, 1, 1, 0), msg(3, 2, 1, 1)
    buf.add(msg(2, 1, 1, 0))
    buf.add(first)
    buf.add(msg(4, 1, 1, 0))
    buf.add(second)
    taken, dropped = buf.take(3)
    assert taken == [first, second]
    assert dropped == 1  # round 2 was skipped here
    assert buf.rounds() == [4]


def test_an_early_buffer_of_size_zero_keeps_nothing() -> None:
    assert EarlyBuffer(per_round=0).add(msg(1, 0, 0, 0)) == (False, 0)


# --- rounds and the neighbour check --------------------------------------------------


def test_start_round_broadcasts_the_own_output_with_hop_count_zero_to_each_neighbour() -> None:
    r = robot(2, 5)
    started = r.start_round(7, UNIFORM, 0.5, [3, 1, 3])
    assert started.broadcast.targets == (1, 3)
    m = started.broadcast.message
    assert (m.round_id, m.origin, m.sender, m.hops, m.yaw) == (7, 2, 2, 0, 0.5)
    assert started.early == () and started.stale == 0


def test_a_message_from_a_robot_that_is_not_a_neighbour_is_rejected_and_not_recorded() -> None:
    r = robot(0, 5)
    r.start_round(1, UNIFORM, 0.0, [1])
    handled = r.receive(msg(1, 2, 2, 0))  # robot 2 is two hops away on a line
    assert (handled.outcome, handled.reason) == (Handling.REJECTED, "not_neighbour")
    # The same origin relayed by the neighbour is still new.
    ok = r.receive(msg(1, 2, 1, 1))
    assert ok.outcome is Handling.ACCEPTED and ok.step is not None
    assert (ok.step.origin, ok.step.sender, ok.step.hops) == (2, 1, 2)
    record = r.record()
    assert record is not None and record.rejected == 1 and len(record.steps) == 1


def test_an_accepted_message_is_forwarded_to_every_neighbour_with_one_more_hop() -> None:
    r = robot(1, 3)
    r.start_round(1, UNIFORM, 0.0, [0, 2])
    handled = r.receive(msg(1, 0, 0, 0))
    assert handled.broadcast is not None
    assert handled.broadcast.targets == (0, 2)  # a broadcast reaches its sender too (Algorithm 1)
    fwd = handled.broadcast.message
    assert (fwd.origin, fwd.sender, fwd.hops) == (0, 1, 1)


def test_copies_of_a_heard_origin_and_of_the_own_output_are_duplicates() -> None:
    r = robot(1, 3)
    r.start_round(1, UNIFORM, 0.0, [0, 2])
    r.receive(msg(1, 0, 0, 0))
    assert r.receive(msg(1, 0, 2, 2)).outcome is Handling.DUPLICATE
    assert r.receive(msg(1, 1, 0, 1)).outcome is Handling.DUPLICATE  # own output echoed back
    record = r.record()
    assert record is not None and record.duplicates == 2


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (msg(1, 1, 1, 1), "bad_hops"),  # an origin sends hop count 0
        (msg(1, 2, 1, 0), "bad_hops"),  # only an origin sends hop count 0
        (msg(1, 2, 1, 9), "bad_hops"),  # more hops than robots (the core's check)
        (msg(1, 7, 1, 1), "bad_origin"),
        (msg(1, 1, 1, 0, [math.nan] * N_CLASSES), "not_finite"),
        (msg(1, 1, 1, 0, [0.5, 0.5]), "wrong_length"),
        (msg(1, 1, 1, 0, [0.5] * N_CLASSES), "not_normalised"),
        (FloodMessage(1, 1, 1, 0, math.inf, UNIFORM), "bad_yaw"),
    ],
)
def test_malformed_messages_are_rejected_with_a_reason_and_leave_the_round_intact(
    message: FloodMessage, reason: str
) -> None:
    r = robot(0, 3)
    r.start_round(1, UNIFORM, 0.0, [1])
    handled = r.receive(message)
    assert (handled.outcome, handled.reason) == (Handling.REJECTED, reason)
    # The origin was not recorded: a good copy is still accepted.
    assert r.receive(msg(1, 1, 1, 0)).outcome is Handling.ACCEPTED


def test_a_message_of_an_earlier_round_is_stale() -> None:
    r = robot(0, 3)
    r.start_round(1, UNIFORM, 0.0, [1])
    r.start_round(2, UNIFORM, 0.0, [1])
    handled = r.receive(msg(1, 1, 1, 0))
    assert (handled.outcome, handled.reason) == (Handling.REJECTED, "stale_round")


def test_messages_that_arrive_before_their_round_starts_are_processed_when_it_starts() -> None:
    r = robot(0, 3)
    assert r.receive(msg(1, 1, 1, 0)).outcome is Handling.BUFFERED
    assert r.receive(msg(1, 2, 2, 0)).outcome is Handling.BUFFERED  # robot 2: not a neighbour, found later
    assert r.receive(msg(1, 2, 1, 1)).outcome is Handling.BUFFERED
    started = r.start_round(1, UNIFORM, 0.0, [1])
    assert [(h.outcome, h.reason) for h in started.early] == [
        (Handling.ACCEPTED, ""),
        (Handling.REJECTED, "not_neighbour"),  # neighbours are known only at the start
        (Handling.ACCEPTED, ""),
    ]
    record = r.record()
    assert record is not None and [(s.origin, s.hops) for s in record.steps] == [(1, 1), (2, 2)]
    # Each step knows its own place, though all were folded in before any was reported.
    assert [s.incorporated for s in record.steps] == [1, 2]


def test_a_round_started_again_or_out_of_order_is_refused() -> None:
    r = robot(0, 3)
    r.start_round(5, UNIFORM, 0.0, [1])
    for round_id in (5, 4):
        with pytest.raises(RoundError, match="round ids must advance: round 5 runs now"):
            r.start_round(round_id, UNIFORM, 0.0, [1])


def test_a_new_round_id_may_jump_at_most_max_round_jump_ahead() -> None:
    r = FusionRobot(0, 3, law=make_weight_law("paper"), n_classes=N_CLASSES, max_round_jump=10)
    r.start_round(5, UNIFORM, 0.0, [1])
    with pytest.raises(RoundError, match=r"is 6 to 15 \(at most 10 ahead, modulo 2\^32\), got 16"):
        r.start_round(16, UNIFORM, 0.0, [1])
    with pytest.raises(RoundError, match="got 4294967295"):
        r.start_round(2**32 - 1, UNIFORM, 0.0, [1])  # the id that used to lock the robot
    current = r.record()
    assert current is not None and current.round_id == 5  # nothing changed
    r.start_round(15, UNIFORM, 0.0, [1])


def test_round_ids_count_modulo_2_to_the_32_so_no_round_id_locks_the_robot() -> None:
    # A fresh robot takes any first round, 2^32 - 1 included; the next is 0, not "nothing".
    r = robot(0, 3)
    r.start_round(2**32 - 1, UNIFORM, 0.0, [1])
    assert r.receive(msg(0, 1, 1, 0)).outcome is Handling.BUFFERED  # round 0 comes next
    assert r.receive(msg(2**32 - 2, 1, 1, 0)).reason == "stale_round"  # one before
    started = r.start_round(0, UNIFORM, 0.0, [1])
    assert [h.outcome for h in started.early] == [Handling.ACCEPTED]
    r.start_round(3, UNIFORM, 0.0, [1])
    with pytest.raises(RoundError, match="round ids must advance"):
        r.start_round(2**32 - 1, UNIFORM, 0.0, [1])  # behind now
    with pytest.raises(RoundError, match="32-bit"):
        r.start_round(2**32, UNIFORM, 0.0, [1])


def test_a_message_more_than_max_round_jump_ahead_is_refused_not_kept() -> None:
    r = FusionRobot(0, 3, law=make_weight_law("paper"), n_classes=N_CLASSES, max_round_jump=10)
    r.start_round(5, UNIFORM, 0.0, [1])
    assert r.receive(msg(15, 1, 1, 0)).outcome is Handling.BUFFERED
    far = r.receive(msg(16, 1, 1, 0))
    assert (far.outcome, far.reason) == (Handling.REJECTED, "too_far_ahead")
    assert r.receive(msg(2**31, 1, 1, 0)).reason == "too_far_ahead"
    assert r.receive(msg(4, 1, 1, 0)).reason == "stale_round"
    assert len(r.buffer) == 1


def test_starting_a_round_drops_kept_messages_of_rounds_it_cannot_reach() -> None:
    # Before the first round any round is kept; once round 3 starts, rounds outside
    # 4 .. 3 + max_round_jump cannot follow it and are dropped as stale.
    r = FusionRobot(0, 3, law=make_weight_law("paper"), n_classes=N_CLASSES, max_round_jump=10)
    for round_id in (1, 3, 9, 2**32 - 1):
        assert r.receive(msg(round_id, 1, 1, 0)).outcome is Handling.BUFFERED
    started = r.start_round(3, UNIFORM, 0.0, [1])
    assert (len(started.early), started.stale) == (1, 2)
    assert r.buffer.rounds() == [9]


@pytest.mark.parametrize(
    ("probs", "yaw", "neighbours", "match"),
    [
        ([0.5, 0.5], 0.0, [1], "expected 5 class scores"),
        ([0.3] * N_CLASSES, 0.0, [1], "must sum to 1"),
        ([math.nan] * N_CLASSES, 0.0, [1], "NaN"),
        (UNIFORM, math.nan, [1], "yaw must be finite"),
        (UNIFORM, 0.0, [0], r"neighbours must be other robots .* got \[0\]"),
        (UNIFORM, 0.0, [1, 3], r"got \[3\]"),
    ],
)
def test_a_bad_start_round_is_refused_with_a_clear_message(
    probs: list[float], yaw: float, neighbours: list[int], match: str
) -> None:
    r = robot(0, 3)
    with pytest.raises(RoundError, match=match):
        r.start_round(1, probs, yaw, neighbours)
    assert r.record() is None


def test_with_r_max_a_message_at_the_limit_is_kept_but_not_forwarded() -> None:
    r = robot(1, 4, r_max=2)
    r.start_round(1, UNIFORM, 0.0, [0, 2])
    handled = r.receive(msg(1, 3, 2, 1))  # arrives at 2 hops = r_max
    assert handled.outcome is Handling.ACCEPTED and handled.broadcast is None


def test_only_the_last_rounds_are_kept_for_the_posterior_endpoint() -> None:
    r = robot(0, 2)
    for round_id in range(KEPT_ROUNDS + 3):
        r.start_round(round_id, UNIFORM, 0.0, [1])
    assert r.rounds_kept == KEPT_ROUNDS
    assert r.record(0) is None
    latest = r.record()
    assert latest is not None and latest.round_id == KEPT_ROUNDS + 2
    assert r.record(3) is not None


# --- the wire form ------------------------------------------------------------------


def test_a_received_vector_is_forwarded_bit_identical() -> None:
    rng = np.random.default_rng(1)
    sent = flood_to_classifier_output(FloodMessage(3, 2, 2, 0, 0.123456789, probabilities(rng)))
    received = classifier_output_to_flood(type(sent).FromString(sent.SerializeToString()))
    forwarded = flood_to_classifier_output(FloodMessage(3, 2, 4, 1, received.yaw, received.likelihood))
    assert list(forwarded.probabilities) == list(sent.probabilities)
    assert forwarded.yaw_rad == sent.yaw_rad
    assert (forwarded.hop_count, forwarded.sender_robot_id, forwarded.origin_robot_id) == (1, 4, 2)


# --- a whole flood on an emulated bus -------------------------------------------------


def flood_on_emulated_bus(
    neighbours: list[list[int]], seed: int, *, start_late: bool
) -> tuple[list[FusionRobot], list[np.ndarray], list[float], int]:
    """Every robot of the graph on a bus that delivers in a random order; with
    ``start_late`` robots start their round one by one while messages already fly.
    Returns the robots, their outputs and yaws, and how many messages came early."""
    n = len(neighbours)
    rng = np.random.default_rng(seed)
    order = random.Random(seed)
    robots = [robot(i, n, early=64) for i in range(n)]
    probs = [probabilities(rng) for _ in range(n)]
    yaws = [float(np.float32(y)) for y in rng.uniform(-math.pi, math.pi, n)]
    in_flight: deque[tuple[int, FloodMessage]] = deque()
    early = 0

    def send(b: Broadcast | None) -> None:
        if b is not None:
            in_flight.extend((t, b.message) for t in b.targets)

    def handle(h: Handled) -> None:
        if h.outcome is Handling.ACCEPTED:
            send(h.broadcast)

    def start(i: int) -> None:
        nonlocal early
        started = robots[i].start_round(1, probs[i], yaws[i], neighbours[i])
        send(started.broadcast)
        early += len(started.early)
        for h in started.early:
            handle(h)

    pending = list(range(n))
    order.shuffle(pending)
    if not start_late:
        for i in pending:
            start(i)
        pending = []
    while in_flight or pending:
        if pending and (not in_flight or order.random() < 0.3):
            start(pending.pop())
            continue
        k = order.randrange(len(in_flight))
        in_flight.rotate(-k)
        target, message = in_flight.popleft()
        handle(robots[target].receive(message))
    return robots, probs, yaws, early


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("start_late", [False, True])
def test_on_a_line_any_delivery_order_gives_exact_hops_duplicates_and_the_cores_posterior(
    seed: int, start_late: bool
) -> None:
    n = 5
    neighbours = line(n)
    robots, probs, yaws, early = flood_on_emulated_bus(neighbours, seed, start_late=start_late)
    assert (early > 0) == start_late  # late starts do exercise the early buffer
    law = make_weight_law("paper", lam=1.0)
    for i, r in enumerate(robots):
        record = r.record()
        assert record is not None
        assert sorted((s.origin, s.hops) for s in record.steps) == [
            (j, abs(i - j)) for j in range(n) if j != i
        ]
        assert all(s.sender in neighbours[i] for s in record.steps)
        # Each robot broadcasts each of the n outputs once to each neighbour: every
        # robot receives n copies from each neighbour and keeps n - 1 of them.
        assert record.duplicates == n * len(neighbours[i]) - (n - 1)
        assert record.rejected == 0
        core = FusionState(probs[i], yaws[i], law, own_id=i)
        for s in record.steps:
            core.incorporate(s.origin, probs[s.origin], s.hops, yaws[s.origin])
        assert np.array_equal(core.posterior, record.state.posterior)


def test_in_lock_step_the_robots_hear_what_the_cores_simulator_hears() -> None:
    n = 5
    neighbours = line(n)
    robots, probs, yaws, _ = flood_on_emulated_bus(neighbours, 0, start_late=False)
    adj = np.zeros((n, n), bool)
    for i, ns in enumerate(neighbours):
        adj[i, ns] = True
    sim = simulate_flooding(adj, np.array(probs), np.array(yaws))
    for i, r in enumerate(robots):
        record = r.record()
        assert record is not None
        assert sorted((s.origin, s.hops) for s in record.steps) == sorted(sim.order(i))
        assert record.duplicates == sim.duplicates[i]


# --- settings -----------------------------------------------------------------------


def test_the_fusion_settings_default_to_the_papers_street() -> None:
    s, c = FusionSettings(), LandmarkSettings()
    assert (c.n_classes, s.fusion_law, s.fusion_lambda, s.fusion_r_max) == (19, "paper", None, 0)


def test_the_fusion_settings_come_from_the_environment_like_any_other() -> None:
    env = {"SWARMREC_FUSION_LAW": "agreement", "SWARMREC_FUSION_LAMBDA": "1.5", "SWARMREC_N_CLASSES": "7"}
    config = load_config((FusionSettings, LandmarkSettings), env=env)
    s = config.get(FusionSettings)
    assert (s.fusion_law, s.fusion_lambda, config.get(LandmarkSettings).n_classes) == ("agreement", 1.5, 7)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"n_classes": 1}, "n_classes must be >= 2"),
        ({"fusion_law": "loudest"}, "fusion_law must be paper or agreement"),
        ({"fusion_lambda": -1.0}, "fusion_lambda must be finite and >= 0"),
        ({"fusion_lambda": math.nan}, "fusion_lambda must be finite and >= 0"),
        ({"fusion_r_max": -1}, "fusion_r_max must be >= 0"),
        ({"fusion_early_messages": -1}, "fusion_early_messages must be >= 0"),
        ({"fusion_max_round_jump": 0}, r"fusion_max_round_jump must be in \[1, 2\^31\)"),
        ({"fusion_max_round_jump": 2**31}, r"fusion_max_round_jump must be in \[1, 2\^31\)"),
    ],
)
def test_bad_fusion_settings_are_refused(changes: dict[str, object], match: str) -> None:
    component = LandmarkSettings if "n_classes" in changes else FusionSettings
    with pytest.raises(ConfigError, match=match):
        component(**changes)  # type: ignore[arg-type]


# --- a weight law for one round -------------------------------------------------------


def test_a_round_can_use_its_own_weight_law_and_the_next_falls_back_to_the_robots() -> None:
    from swarmrec.fusion import PaperWeightLaw

    r = robot(0, 3)  # its own law: paper, lambda 1
    own = [0.6, 0.1, 0.1, 0.1, 0.1]
    heard = [0.1, 0.6, 0.1, 0.1, 0.1]
    r.start_round(1, own, 0.0, [1], law=PaperWeightLaw(lam=0.0))
    r.receive(FloodMessage(1, 1, 1, 0, 0.0, np.array(heard)))
    # lambda 0 and equal yaws: weight 1, plain naive Bayes: own * heard, normalised.
    naive = np.array(own) * np.array(heard)
    np.testing.assert_allclose(r.record(1).state.posterior, naive / naive.sum(), atol=1e-12)  # type: ignore[union-attr]
    r.start_round(2, own, 0.0, [1])
    r.receive(FloodMessage(2, 1, 1, 0, 0.0, np.array(heard)))
    # lambda 1, one hop: weight (1 + 1)^-1 = 0.5, the mixture of Eq. 12.
    mixed = 0.5 * naive / naive.sum() + 0.5 * np.array(own)
    np.testing.assert_allclose(r.record(2).state.posterior, mixed, atol=1e-12)  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("name", "lam", "match"),
    [("magic", None, "unknown weight law"), ("paper", -1.0, "lambda"), ("paper", math.nan, "lambda")],
)
def test_a_round_law_that_does_not_exist_is_a_config_error(name: str, lam: float | None, match: str) -> None:
    from swarmrec.wire import messages as pb

    spec = pb.WeightLaw(name=name)
    if lam is not None:
        setattr(spec, "lambda", lam)
    with pytest.raises(ConfigError, match=match):
        weight_law_from_proto(spec)


def test_a_round_law_names_the_law_and_its_lambda() -> None:
    from swarmrec.fusion import PaperWeightLaw
    from swarmrec.wire import messages as pb

    assert weight_law_from_proto(pb.WeightLaw(name="paper")) == PaperWeightLaw(lam=2.0)
    spec = pb.WeightLaw(name="paper")
    setattr(spec, "lambda", 100.0)
    assert weight_law_from_proto(spec) == PaperWeightLaw(lam=100.0)
    assert weight_law_from_proto(pb.WeightLaw(name="agreement")).name == "agreement"


def test_a_message_the_bus_says_came_from_someone_else_is_rejected_and_counted_in_the_round() -> None:
    from swarmrec.fusion.robot import Reason

    r = robot(0, 3)
    r.start_round(1, UNIFORM, 0.0, [1])
    handled = r.reject(Reason.SENDER_MISMATCH, msg(1, 1, 1, 0))
    assert (handled.outcome, handled.reason) == (Handling.REJECTED, "sender_mismatch")
    record = r.record()
    assert record is not None and record.rejected == 1 and record.steps == []
    # The true robot 1's copy is still welcome.
    assert r.receive(msg(1, 1, 1, 0)).outcome is Handling.ACCEPTED
