"""The offline side of a split team (swarmrec.evaluation.partition): what each owner holds
step by step, and the decentralized evaluation on a schedule that splits and heals."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.core.placement import Placement
from swarmrec.core.presets import get_preset
from swarmrec.core.types import ConstellationSequence
from swarmrec.errors import ConfigError
from swarmrec.evaluation.partition import Holdings, Reach
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.synthetic.config import OfficeConfig
from swarmrec.synthetic.office import generate_office

WHOLE = [[0, 1, 2]]
SPLIT = [[0], [1, 2]]


def _one_group(owners: tuple[int, ...]) -> Placement:
    return Placement(version=3, groups=((0, 4),), owners=(owners,), members=(0, 1, 2), replicas=len(owners))


def _holdings(schedule: list[list[list[int]]], owners: tuple[int, ...]) -> Holdings:
    reach = Reach.of(schedule, 3, [0, 4], replicas=2, placements=[(0, _one_group(owners))])
    stored = np.ones((3, len(schedule), 1), bool)  # every robot stores a slice at every step
    return Holdings(reach, stored, [0])


def test_a_store_reaches_the_owners_in_its_part_and_the_rest_once_the_team_heals() -> None:
    h = _holdings([WHOLE, SPLIT, SPLIT, WHOLE], owners=(0, 1))
    for t in range(4):
        h.deliver(t)
        h.store(t)
        if t == 1:
            # Robot 0 stored at step 1 alone with owner 0; robots 1 and 2 with owner 1.
            assert h.held(0, 0)[:, 1].tolist() == [True, False, False]
            assert h.held(1, 0)[:, 1].tolist() == [False, True, True]
        if t == 2:
            # Still split at step 2: nothing crossed.
            assert not h.held(1, 0)[0, 1] and not h.held(0, 0)[1, 1]
    # Healed before step 3: every slice of steps 0-2 is at both owners.
    assert h.held(0, 0)[:, :3].all() and h.held(1, 0)[:, :3].all()


def test_a_query_sees_its_parts_owner_and_nothing_where_its_part_has_none() -> None:
    h = _holdings([WHOLE, SPLIT, SPLIT], owners=(0, 1))
    h.store(0)
    h.deliver(1)
    h.store(1)
    h.deliver(2)
    # Robot 2 at step 2 can only be answered by owner 1, which lacks robot 0's step-1 slice.
    seen = h.visible(2, 0, 2)
    assert seen is not None
    assert seen.reshape(3, 2).tolist() == [[True, False], [True, True], [True, True]]
    # A group owned by robot 0 alone: robots 1 and 2 find no owner while split.
    lone = _holdings([WHOLE, SPLIT], owners=(0,))
    lone.store(0)
    lone.deliver(1)
    assert lone.visible(1, 0, 1) is None and lone.unreached == [(1, 1, 0)]
    assert lone.visible(0, 0, 1) is not None


def test_reachability_follows_the_parts() -> None:
    h = _holdings([WHOLE, SPLIT], owners=(0, 1))
    assert h.reachable(0, 0, np.array([1, 2])).tolist() == [True, True]
    assert h.reachable(0, 1, np.array([0, 1, 2])).tolist() == [True, False, False]
    assert h.reachable(1, 1, np.array([0, 2])).tolist() == [False, True]


def test_a_schedule_must_name_every_robot_and_start_its_placements_at_step_0() -> None:
    with pytest.raises(ConfigError, match="every robot"):
        Reach.of([[[0, 1]]], 3, [0, 4], replicas=2)
    with pytest.raises(ConfigError, match="step 0"):
        Reach(np.zeros((2, 3), np.int64), ((1, _one_group((0, 1))),))


def _world(frames: int = 240) -> ConstellationSequence:
    return generate_office(OfficeConfig(seed=3, n_frames=frames)).sequence


def test_a_team_never_split_scores_exactly_as_the_plain_evaluation() -> None:
    seq = _world()
    preset = get_preset("paper")
    plain = score_decentralized(seq, 4, preset)
    per = plain.frames_per_robot
    reach = Reach.of([[[0, 1, 2, 3]]] * per, 4, plain.bounds.tolist(), replicas=2)
    whole = score_decentralized(seq, 4, preset, reach=reach)
    assert np.array_equal(plain.matrix.pairs_i, whole.matrix.pairs_i)
    assert np.array_equal(plain.matrix.pairs_j, whole.matrix.pairs_j)
    assert np.array_equal(plain.matrix.scores, whole.matrix.scores)
    assert whole.holdings is not None and not whole.holdings.unreached and not whole.holdings.unverified


def test_while_split_no_pair_joins_the_two_parts_and_after_healing_they_do_again() -> None:
    seq = _world()
    preset = get_preset("paper")
    plain = score_decentralized(seq, 4, preset)
    per = plain.frames_per_robot
    lo, hi = 10, 40
    parts = [[[0, 1, 2, 3]]] * lo + [[[0, 1], [2, 3]]] * (hi - lo) + [[[0, 1, 2, 3]]] * (per - hi)
    reach = Reach.of(parts, 4, plain.bounds.tolist(), replicas=2)
    split = score_decentralized(seq, 4, preset, reach=reach)
    m = split.matrix
    robot_i, step_i = m.pairs_i // per, m.pairs_i % per
    robot_j, step_j = m.pairs_j // per, m.pairs_j % per
    side = np.array([0, 0, 1, 1])
    across = side[robot_i] != side[robot_j]
    # The query is the later frame of a pair: none queried across the split while split.
    later = np.maximum(step_i, step_j)
    assert across.any(), "some pairs join the two halves outside the split"
    assert not (across & (later >= lo) & (later < hi)).any()
    assert split.holdings is not None
    assert split.holdings.unverified, "some queries picked a robot across the split"
    # Fewer pairs than the whole team found.
    plain_pairs = set(zip(plain.matrix.pairs_i.tolist(), plain.matrix.pairs_j.tolist(), strict=True))
    split_pairs = set(zip(m.pairs_i.tolist(), m.pairs_j.tolist(), strict=True))
    assert len(split_pairs) < len(plain_pairs)


def test_a_placement_made_while_whole_gives_its_new_owners_every_earlier_slice() -> None:
    first, moved = (
        _one_group((0, 1)),
        Placement(version=4, groups=((0, 4),), owners=((0, 2),), members=(0, 1, 2), replicas=2),
    )
    reach = Reach.of([WHOLE, WHOLE, SPLIT], 3, [0, 4], replicas=2, placements=[(0, first), (2, moved)])
    h = Holdings(reach, np.ones((3, 3, 1), bool), [0])
    for t in range(3):
        h.deliver(t)
        h.store(t)
    # Shard 2 became an owner at step 2 (the handoff done while whole): it copied steps 0-1,
    # then stored only its own part's slice of step 2.
    assert h.held(2, 0).tolist() == [[True, True, False], [True, True, True], [True, True, True]]
    with pytest.raises(ConfigError, match="whole team"):
        Reach.of([WHOLE, SPLIT, SPLIT], 3, [0, 4], replicas=2, placements=[(0, first), (2, moved)])
