"""Conversion between :class:`~swarmrec.core.placement.Placement` and its message.

A placement arrives from the coordinator (or from any shard a client asks); it
is checked here before anyone follows it: groups tile ``[0, n_labels)``, every
list is within bounds, and :class:`~swarmrec.core.placement.Placement` checks
the rest (owners are members, learners own nothing yet, ...). A bad one is a
:class:`~swarmrec.errors.MalformedMessageError`, never a half-followed table.
"""

from __future__ import annotations

import itertools

from swarmrec.core.placement import Placement
from swarmrec.errors import ConfigError, MalformedMessageError
from swarmrec.wire import messages as pb

__all__ = ["MAX_GROUPS", "MAX_SHARD_ID", "placement_from_proto", "placement_to_proto"]

#: Most groups a placement may have (a group per label at most; label lists are smaller).
MAX_GROUPS = 4096
#: Largest shard id (the robot ids' bound).
MAX_SHARD_ID = 999_999
# A group's owners, learners or leaving owners: no more than this many shards.
_MAX_PER_GROUP = 64


def placement_to_proto(p: Placement) -> pb.Placement:
    bounds = [lo for lo, _ in p.groups] + ([p.groups[-1][1]] if p.groups else [])
    return pb.Placement(
        version=p.version,
        group_bounds=bounds,
        groups=[
            pb.GroupOwners(owners=own, learners=learn, leaving=leave)
            for own, learn, leave in zip(p.owners, p.learners, p.leaving, strict=True)
        ],
        members=p.members,
        replicas=p.replicas,
    )


def placement_from_proto(msg: pb.Placement, n_labels: int) -> Placement:
    """The placement in ``msg`` for a label list of ``n_labels``; MalformedMessageError
    naming the first problem."""
    bounds = list(msg.group_bounds)
    if not 2 <= len(bounds) <= MAX_GROUPS + 1:
        raise MalformedMessageError(f"a placement needs 1 to {MAX_GROUPS} groups, got {len(bounds) - 1}")
    if bounds[0] != 0 or bounds[-1] != n_labels:
        raise MalformedMessageError(
            f"a placement's groups must cover labels [0, {n_labels}), got [{bounds[0]}, {bounds[-1]})"
        )
    if len(msg.groups) != len(bounds) - 1:
        raise MalformedMessageError(f"{len(bounds) - 1} groups but {len(msg.groups)} owner lists")
    if len(msg.members) > MAX_GROUPS or any(m > MAX_SHARD_ID for m in msg.members):
        raise MalformedMessageError(f"a placement lists at most {MAX_GROUPS} shards, ids <= {MAX_SHARD_ID}")
    if not 1 <= msg.replicas <= _MAX_PER_GROUP:
        raise MalformedMessageError(f"replicas must be 1 to {_MAX_PER_GROUP}, got {msg.replicas}")
    for g in msg.groups:
        if max(len(g.owners), len(g.learners), len(g.leaving)) > _MAX_PER_GROUP:
            raise MalformedMessageError(f"a group lists at most {_MAX_PER_GROUP} shards")
    try:
        return Placement(
            version=msg.version,
            groups=tuple(itertools.pairwise(bounds)),
            owners=tuple(tuple(g.owners) for g in msg.groups),
            members=tuple(msg.members),
            replicas=msg.replicas,
            learners=tuple(tuple(g.learners) for g in msg.groups),
            leaving=tuple(tuple(g.leaving) for g in msg.groups),
        )
    except ConfigError as e:
        raise MalformedMessageError(str(e)) from None
