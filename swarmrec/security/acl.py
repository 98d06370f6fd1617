"""The router's access control: default deny, one policy per identity.

The router checks every message a node sends it (``ingress``) and every
message it is about to send a node (``egress``) against the rules of the
node's certificate common name (zenoh 1.10 ``access_control``; a rule allows
a message when one of its key expressions *includes* the message's key).
What is allowed is derived from the protocol (docs/security.md has the table):

* the points of control are the ingress side: what a node may put, query,
  reply, and which queryables, subscribers and liveliness tokens it may
  declare. A service declares queryables and replies only under its own
  ``<kind>/<robot>/``, puts only its own robot's events, and queries only
  what its stage calls.
* egress is allowed for the whole swarm prefix: a node is only ever sent
  queries for queryables, and samples for subscribers, that ingress let it
  declare, and it must see the others' declarations or zenoh's writer-side
  filtering drops its own puts and queries before they leave.

The ACL sees key expressions, not payloads: an index-shard ``query`` that
stores looks like one that does not, so clients read shards through their
read-only ``lookup`` endpoint (``shard_read_endpoint``) and only descriptors may
call ``query``. A host (a process running every service of some robots, ``--hosting
robot`` or ``robots:K``) gets the union of its robots' services' rules. A gateway
(``gateways``) is a client that also declares its own ``info`` queryable and liveliness
token under ``gateway/0``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import zenoh

from swarmrec.errors import ConfigError, SecurityError
from swarmrec.runtime import keys
from swarmrec.runtime.tls import insert_access_control
from swarmrec.security.identity import SERVICE_KINDS, Identity
from swarmrec.services import registry

__all__ = [
    "ACL_MESSAGES",
    "SHARD_READ_ENDPOINT",
    "Grant",
    "access_control",
    "configure_access_control",
    "grants",
    "swarm_identities",
]

Flow = Literal["ingress", "egress"]

#: Every message type zenoh 1.10's access control filters.
ACL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)

# What a node may be sent from the rest of the swarm (see the module docstring).
_EGRESS = ("put", "query", "reply", "declare_subscriber", "declare_queryable", "liveliness_token")

# What each kind queries, as (kind, robot, endpoint); "self" is the service's own robot.
_QUERIES: dict[str, tuple[tuple[str, str, str], ...]] = {
    "detector": (
        ("descriptor", "self", "process"),
        ("place-owner", "self", "process"),
        ("fusion", "self", "start_round"),
    ),
    "descriptor": (
        ("index-shard", "*", "query"),
        ("index-shard", "*", "store"),
        ("index-shard", "*", "placement"),
        ("verifier", "*", "verify"),
        ("verifier", "self", "store"),
    ),
    # The elastic index: shards read each other's placement, the coordinator sends
    # placements, a shard copying a group pages through an owner's copy.
    "index-shard": (
        ("index-shard", "*", "placement"),
        ("index-shard", "*", "adopt"),
        ("index-shard", "*", "transfer"),
    ),
    "verifier": (),
    # Full-image place recognition: the owner of a query's cluster, the verifier of its match.
    "place-owner": (
        ("place-owner", "*", "query"),
        ("verifier", "*", "verify"),
        ("verifier", "self", "store"),
    ),
    "fusion": (),
    "slam": (),
}

# Read-only endpoints every client may query (shards' are added per call).
_CLIENT_QUERIES = (
    ("*", "info"),
    ("index-shard", "placement"),
    ("verifier", "verify"),
    ("descriptor", "loop_closures"),
    ("descriptor", "explain"),
    ("place-owner", "assignment"),
    ("place-owner", "loop_closures"),
    ("fusion", "posterior"),
    ("slam", "status"),
    ("slam", "estimate"),
    ("slam", "sent"),
)
# What an operator adds: driving the replay (lock-step steps, free replay, classifier views)
# and the distributed SLAM solves.
_OPERATOR_QUERIES = (
    ("detector", "step"),
    ("detector", "replay"),
    ("detector", "classify"),
    ("slam", "load"),
    ("slam", "solve"),
)


@dataclass(frozen=True)
class Grant:
    """``messages`` a node may send (ingress) or be sent (egress) on ``key_exprs``."""

    flow: Flow
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]


def _prefix(swarm: str) -> str:
    return f"{keys.PREFIX}/{swarm}"


def _robot(spec: str, own: int) -> int | str:
    return own if spec == "self" else spec


#: The shard endpoint clients read through (never stores; see the module docstring).
SHARD_READ_ENDPOINT = "lookup"


def grants(
    identity: Identity,
    robots: Sequence[int],
    *,
    shard_read_endpoint: str = SHARD_READ_ENDPOINT,
    gateway: bool = False,
    kinds: Sequence[str] = SERVICE_KINDS,
) -> list[Grant]:
    """What ``identity`` may do in a swarm of ``robots``; everything else is denied.
    ``gateway``: the identity (a client) hosts the swarm's gRPC gateway. A host may do
    what each of its robots' services (``kinds``) may, and nothing more: so a process
    hosting robots 0..4 can act as any of them, never as robot 5."""
    s, p = identity.swarm, _prefix(identity.swarm)
    out = [Grant("egress", _EGRESS, (f"{p}/**",))]
    if identity.role == "host":
        for r in identity.robots:
            for kind in kinds:
                out += grants(Identity.service(s, kind, r), robots)[1:]  # [0]: the shared egress
        return out
    if identity.role == "service":
        kind, r = identity.kind, identity.robot
        # Its endpoints (caller-bound ones asked and answered at <endpoint>/<caller>).
        own = keys.endpoint(s, kind, r, "**")
        out += [
            Grant("ingress", ("declare_queryable", "reply"), (own,)),
            Grant("ingress", ("liveliness_token",), (keys.alive(s, kind, r),)),
            Grant("ingress", ("put",), (keys.event(s, "*", r),)),
        ]
        # A kind a plugin added serves its own endpoints and calls nothing (no rule for it).
        # A caller-bound endpoint only with this robot as the caller (keys.CALLER_BOUND):
        # so no robot stores, queries or places in another's name.
        queries = tuple(
            keys.request_key(keys.endpoint(s, k, _robot(rob, r), ep), r)
            for k, rob, ep in _QUERIES.get(kind, ())
        )
        if queries:
            out.append(Grant("ingress", ("query",), queries))
        if kind in ("descriptor", "index-shard"):
            # Which shards are alive: descriptors route around gone ones, the coordinator follows them.
            out.append(
                Grant(
                    "ingress",
                    ("declare_liveliness_subscriber", "liveliness_query"),
                    (keys.alive(s, "index-shard", "*"),),
                )
            )
        if kind == "index-shard":
            # A stopping shard says so, and every shard sees who stays to take its groups.
            out += [
                Grant("ingress", ("liveliness_token",), (keys.draining(s, kind, r),)),
                Grant(
                    "ingress",
                    ("declare_liveliness_subscriber", "liveliness_query"),
                    (keys.draining(s, kind, "*"),),
                ),
            ]
        if kind == "fusion":
            # Flooding puts onto the neighbours' inboxes; who is a neighbour
            # changes with the radio graph, so every other robot of the swarm.
            # The key's last segment names the sender (as the SLAM inboxes): no robot puts
            # in another's name.
            inboxes = tuple(keys.endpoint(s, "fusion", j, f"inbox/{r}") for j in robots if j != r)
            out.append(Grant("ingress", ("declare_subscriber",), (keys.endpoint(s, "fusion", r, "inbox/*"),)))
            if inboxes:
                out.append(Grant("ingress", ("put",), inboxes))
        if kind == "slam":
            # A robot puts on every team member's inbox/<self> and control/<self> only, so the
            # key's last segment names the sender and no robot can speak for another.
            own_boxes = tuple(keys.endpoint(s, "slam", r, f"{box}/*") for box in ("inbox", "control"))
            boxes = tuple(
                keys.endpoint(s, "slam", j, f"{box}/{r}")
                for j in robots
                if j != r
                for box in ("inbox", "control")
            )
            out.append(Grant("ingress", ("declare_subscriber",), own_boxes))
            if boxes:
                out.append(Grant("ingress", ("put",), boxes))
            # Team members that vanish mid-solve: their liveliness tokens.
            out.append(
                Grant(
                    "ingress",
                    ("declare_liveliness_subscriber", "liveliness_query"),
                    (keys.alive(s, "slam", "*"),),
                )
            )
    elif identity.role in ("client", "operator"):
        plugins = [(e.kind, ep) for e in registry.REGISTRY.values() for ep in e.client_endpoints]
        ends = [*_CLIENT_QUERIES, *plugins, ("index-shard", shard_read_endpoint)]
        if identity.role == "operator":
            ends += _OPERATOR_QUERIES
        out += [
            Grant("ingress", ("query",), tuple(keys.endpoint(s, k, "*", ep) for k, ep in ends)),
            Grant("ingress", ("declare_subscriber",), (f"{p}/events/**",)),
            Grant("ingress", ("liveliness_query", "declare_liveliness_subscriber"), (keys.alive_all(s),)),
        ]
        if gateway:
            out += [
                Grant("ingress", ("declare_queryable", "reply"), (keys.endpoint(s, "gateway", 0, "*"),)),
                Grant("ingress", ("liveliness_token",), (keys.alive(s, "gateway", 0),)),
            ]
    else:
        # A router dialling this one (several routers) is not a client: no rules
        # yet, so default deny applies until router-to-router links are designed.
        return []
    return out


def swarm_identities(
    swarm: str,
    robots: Sequence[int],
    *,
    kinds: Sequence[str] = SERVICE_KINDS,
    clients: Sequence[str] = (),
    operators: Sequence[str] = (),
    hosts: Sequence[tuple[int, int]] = (),
) -> list[Identity]:
    """Every identity the ACL names: each robot's services, the hosts (first, last robot),
    clients, operators."""
    out = [Identity.service(swarm, k, r) for r in robots for k in kinds]
    out += [Identity.host(swarm, first, last) for first, last in hosts]
    out += [Identity.client(swarm, n) for n in clients]
    out += [Identity.operator(swarm, n) for n in operators]
    return out


def _robots(robots: int | Iterable[int]) -> list[int]:
    ids = list(range(robots)) if isinstance(robots, int) else sorted(set(robots))
    if not ids:
        raise ConfigError("the ACL needs at least one robot")
    return ids


def access_control(
    swarm: str,
    robots: int | Iterable[int],
    *,
    kinds: Sequence[str] = SERVICE_KINDS,
    clients: Sequence[str] = (),
    operators: Sequence[str] = (),
    gateways: Sequence[str] = (),
    hosts: Sequence[tuple[int, int]] = (),
    shard_read_endpoint: str = SHARD_READ_ENDPOINT,
) -> dict[str, Any]:
    """The ``access_control`` section of the router's zenoh config.

    ``robots`` is a count (ids 0..n-1) or the ids; ``gateways`` are client names that
    host the gRPC gateway (clients too, listed or not in ``clients``); ``hosts`` are the
    (first, last) robots of processes that host several robots' services. Each identity becomes a
    subject matched on its certificate CN, with one policy holding its rules;
    a certificate whose CN is not listed, or a connection without one, gets
    the default: deny.
    """
    keys.validate_swarm_name(swarm)
    ids = _robots(robots)
    for first, last in hosts:
        if first > last or first not in ids or last not in ids:
            raise ConfigError(f"a host's robots {first}..{last} must be robots of the swarm")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    every_client = [*clients, *(g for g in gateways if g not in clients)]
    for ident in swarm_identities(
        swarm, ids, kinds=kinds, clients=every_client, operators=operators, hosts=hosts
    ):
        cn = ident.common_name
        rule_ids = []
        hosts_gateway = ident.role == "client" and ident.name in gateways
        for n, g in enumerate(
            grants(ident, ids, shard_read_endpoint=shard_read_endpoint, gateway=hosts_gateway, kinds=kinds)
        ):
            rule_ids.append(f"{cn}/{n}")
            rules.append(
                {
                    "id": rule_ids[-1],
                    "permission": "allow",
                    "flows": [g.flow],
                    "messages": list(g.messages),
                    "key_exprs": list(g.key_exprs),
                }
            )
        subjects.append({"id": cn, "cert_common_names": [cn]})
        policies.append({"id": cn, "rules": rule_ids, "subjects": [cn]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def configure_access_control(conf: zenoh.Config, acl: Mapping[str, Any]) -> None:
    """Put ``acl`` (from :func:`access_control`) into a router's ``conf``.

    Zenoh checks the section's shape here (an unknown field or message name
    raises) and its consistency (unknown rule or subject ids, duplicate ids)
    only at ``zenoh.open``.
    """
    try:
        insert_access_control(conf, acl)
    except SecurityError as e:
        raise ConfigError(str(e)) from None
