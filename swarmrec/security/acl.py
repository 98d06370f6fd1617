"""The router's access control: default deny, one policy per identity.

The router checks every message a node sends it (``ingress``) and every
message it is about to send a node (``egress``) against the rules of the
node's certificate common name (zenoh 1.10 ``access_control``; a rule allows
a message when one of its key expressions *includes* the message's key).
What is allowed is derived from what each kind's registry entry declares
(:class:`~swarmrec.services.registry.ServiceSpec`: the endpoints it calls, those clients
and the operator may call, the liveliness it follows, its mailboxes), so a plugin's kind
gets rules as a built-in one does (docs/security.md has the table):

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

# What any client may query of every kind: what the service says of itself.
_EVERY_KIND_CLIENT_ENDPOINTS = ("info",)


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
        out += _service_grants(identity, robots)
    elif identity.role in ("client", "operator"):
        entries = registry.REGISTRY.values()
        ends = [("*", ep) for ep in _EVERY_KIND_CLIENT_ENDPOINTS]
        ends += [(e.kind, ep) for e in entries for ep in e.client_endpoints]
        ends.append(("index-shard", shard_read_endpoint))
        if identity.role == "operator":
            ends += [(e.kind, ep) for e in entries for ep in e.operator_endpoints]
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
    elif identity.role == "router" and identity.robot >= 0:
        # Another robot's router (the mesh, docs/mesh.md): it relays every robot's traffic,
        # so it may send anything under the swarm's prefix, and nothing outside it (no one
        # else's admin space). The entry router of each robot checked that robot's own
        # services against their rules before the first hop.
        out.append(Grant("ingress", ACL_MESSAGES, (f"{p}/**",)))
        out[0] = Grant("egress", ACL_MESSAGES, (f"{p}/**",))
    else:
        # The star's one router dials no other: it has no rules, and default deny applies.
        return []
    return out


def _service_grants(identity: Identity, robots: Sequence[int]) -> list[Grant]:
    """What robot ``identity.robot``'s service of ``identity.kind`` may send, from what its
    registry entry declares (:class:`~swarmrec.services.registry.ServiceSpec`: calls,
    watches, mailboxes, drains): a plugin's kind is treated as a built-in one."""
    s, kind, r = identity.swarm, identity.kind, identity.robot
    entry = registry.REGISTRY.get(kind)
    # Its endpoints (caller-bound ones asked and answered at <endpoint>/<caller>), its
    # liveliness token, its events.
    out = [
        Grant("ingress", ("declare_queryable", "reply"), (keys.endpoint(s, kind, r, "**"),)),
        Grant("ingress", ("liveliness_token",), (keys.alive(s, kind, r),)),
        Grant("ingress", ("put",), (keys.event(s, "*", r),)),
    ]
    if entry is None:
        return out  # a kind nobody registered here calls nothing
    # A caller-bound endpoint only with this robot as the caller (keys.CALLER_BOUND): so no
    # robot stores, queries or places in another's name.
    queries = tuple(
        keys.request_key(keys.endpoint(s, c.kind, r if c.own else "*", c.endpoint), r) for c in entry.calls
    )
    if queries:
        out.append(Grant("ingress", ("query",), queries))
    watching = ("declare_liveliness_subscriber", "liveliness_query")
    for watched in entry.watches:
        out.append(Grant("ingress", watching, (keys.alive(s, watched, "*"),)))
    if entry.drains:
        # A stopping member says so, and every member sees who stays to take over.
        out += [
            Grant("ingress", ("liveliness_token",), (keys.draining(s, kind, r),)),
            Grant("ingress", watching, (keys.draining(s, kind, "*"),)),
        ]
    if entry.mailboxes:
        own_boxes = tuple(keys.endpoint(s, kind, r, f"{box}/*") for box in entry.mailboxes)
        boxes = tuple(
            keys.endpoint(s, kind, j, f"{box}/{r}") for j in robots if j != r for box in entry.mailboxes
        )
        out.append(Grant("ingress", ("declare_subscriber",), own_boxes))
        if boxes:
            out.append(Grant("ingress", ("put",), boxes))
    return out


def swarm_identities(
    swarm: str,
    robots: Sequence[int],
    *,
    kinds: Sequence[str] = SERVICE_KINDS,
    clients: Sequence[str] = (),
    operators: Sequence[str] = (),
    hosts: Sequence[tuple[int, int]] = (),
    robot_routers: bool = False,
) -> list[Identity]:
    """Every identity the ACL names: each robot's services, the hosts (first, last robot),
    clients, operators, and with ``robot_routers`` each robot's own router (the mesh)."""
    out = [Identity.service(swarm, k, r) for r in robots for k in kinds]
    if robot_routers:
        out += [Identity.router(swarm, r) for r in robots]
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
    robot_routers: bool = False,
) -> dict[str, Any]:
    """The ``access_control`` section of the router's zenoh config (every router's, in a
    mesh: ``robot_routers`` adds each robot's own router as a relaying peer).

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
        swarm,
        ids,
        kinds=kinds,
        clients=every_client,
        operators=operators,
        hosts=hosts,
        robot_routers=robot_routers,
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
