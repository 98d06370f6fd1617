"""Key expressions of the v1 swarm.

Every key starts with ``swarmrec/v1/<swarm>``: the schema version and the
swarm name are part of every route, so two swarms (or two schema versions)
sharing one router never see each other's messages.

    swarmrec/v1/<swarm>/<kind>/<robot>/<endpoint>     request/response (queryables), and the
                                                      subscriptions a service declares beside its
                                                      endpoints (fusion/<robot>/inbox: flooded outputs)
    swarmrec/v1/<swarm>/<kind>/<robot>/<endpoint>/<caller>
                                                      a request to a caller-bound endpoint
                                                      (``CALLER_BOUND``): the sender's robot last
    swarmrec/v1/<swarm>/alive/<kind>/<robot>          liveliness token, one per service
    swarmrec/v1/<swarm>/events/<event>/<robot>        published events

The service kinds are the registry's (:mod:`swarmrec.services.registry`).
"""

from __future__ import annotations

import re

from swarmrec.errors import ConfigError

__all__ = [
    "CALLER_BOUND",
    "PREFIX",
    "alive",
    "alive_all",
    "bound_caller",
    "caller_bound",
    "endpoint",
    "event",
    "parse_alive",
    "parse_event",
    "parse_sender",
    "request_key",
    "validate_swarm_name",
]

PREFIX = "swarmrec/v1"

_SWARM_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def validate_swarm_name(name: str) -> str:
    """``name`` if it is one plain key segment, else ConfigError.

    Wildcards and slashes in a swarm name would make its keys match another
    swarm's, which is exactly what the name is there to prevent.
    """
    if not _SWARM_NAME.fullmatch(name):
        raise ConfigError(f"swarm name must be 1-64 of A-Z a-z 0-9 _ -, got {name!r}")
    return name


def _robot(robot: int | str) -> str:
    return "*" if robot == "*" else str(int(robot))


def endpoint(swarm: str, kind: str, robot: int | str, name: str) -> str:
    """Key of a service's request/response endpoint (``robot="*"``: every robot)."""
    return f"{PREFIX}/{swarm}/{kind}/{_robot(robot)}/{name}"


#: Endpoints that act for the robot that calls them: a shard stores the querying robot's
#: slices (``query``, ``store``) and takes a placement from the coordinator (``adopt``), a
#: place owner stores the querying robot's descriptor (``query``, ``store_copy``), takes a
#: table from the coordinator (``adopt_table``) and entries from their holder
#: (``store_entries``). A request to one goes to
#: ``<endpoint key>/<caller's robot>``, and the router's access control lets each
#: certificate send them under its own robot(s) only; the service takes the caller from
#: the key, not from what the message or its attachment claims (docs/security.md).
CALLER_BOUND: frozenset[tuple[str, str]] = frozenset(
    {
        ("index-shard", "query"),
        ("index-shard", "store"),
        ("index-shard", "adopt"),
        ("place-owner", "query"),
        ("place-owner", "store_copy"),
        ("place-owner", "adopt_table"),
        ("place-owner", "store_entries"),
    }
)


def caller_bound(kind: str, name: str) -> bool:
    """Whether ``kind``'s endpoint ``name`` takes its caller from the key."""
    return (kind, name) in CALLER_BOUND


def request_key(key: str, caller: int | str | None) -> str:
    """The key a request to endpoint ``key`` goes to: with the caller's robot (``"*"``:
    any robot's, for access rules) appended when the endpoint is caller-bound."""
    parts = key.split("/")
    if caller is None or len(parts) != 6 or not caller_bound(parts[3], parts[5]):
        return key
    return f"{key}/{_robot(caller)}"


def bound_caller(key: str) -> int | None:
    """The caller's robot a caller-bound request's key names (its last chunk); None when
    the key names none."""
    parts = key.split("/")
    return _robot_id(parts[6], 10) if len(parts) == 7 else None


def _robot_id(text: str, max_digits: int) -> int | None:
    """A robot id written in ASCII digits (at most ``max_digits``); None for anything else
    (``"²".isdigit()`` holds, and ``int`` refuses it)."""
    ok = text.isascii() and text.isdigit() and len(text) <= max_digits
    return int(text) if ok else None


def parse_sender(key: str) -> int | None:
    """The robot an inbox key names as the sender (``slam/<r>/inbox/<sender>``,
    ``fusion/<r>/inbox/<sender>``: its last segment, at most 6 digits); None when it names
    none. The router lets each robot's certificate put there under its own robot only."""
    return _robot_id(key.rsplit("/", 1)[-1], 6)


def alive(swarm: str, kind: str, robot: int | str) -> str:
    """Key of a service's liveliness token (``robot`` ``"*"``: of every robot's)."""
    return f"{PREFIX}/{swarm}/alive/{kind}/{_robot(robot)}"


def draining(swarm: str, kind: str, robot: int | str) -> str:
    """Key of the liveliness token a stopping service declares while it still serves
    (an index shard handing its groups on; ``robot`` ``"*"``: every robot's)."""
    return f"{PREFIX}/{swarm}/draining/{kind}/{_robot(robot)}"


def parse_draining(key: str) -> int | None:
    """The robot of a draining token key, None for any other key."""
    parsed = _parse_token(key, "draining")
    return None if parsed is None else parsed[1]


def alive_all(swarm: str) -> str:
    """Selector of every liveliness token of a swarm."""
    return f"{PREFIX}/{swarm}/alive/**"


def parse_alive(key: str) -> tuple[str, int] | None:
    """(kind, robot) of a liveliness token key, None for any other key."""
    return _parse_token(key, "alive")


def _parse_token(key: str, segment: str) -> tuple[str, int] | None:
    """(kind, robot) of a ``<prefix>/<swarm>/<segment>/<kind>/<robot>`` token key."""
    parts = key.split("/")
    if len(parts) != 6 or parts[3] != segment or not parts[5].isdigit():
        return None
    return parts[4], int(parts[5])


def event(swarm: str, name: str, robot: int | str) -> str:
    """Key of a published event (``robot="*"``: every robot)."""
    return f"{PREFIX}/{swarm}/events/{name}/{_robot(robot)}"


def parse_event(key: str) -> tuple[str, int] | None:
    """(event name, robot) of a published event's key, None for any other key. The router
    lets a robot's services publish on their own robot's keys only, so the key's robot is
    the publisher's; a payload that names another robot is a forgery."""
    return _parse_token(key, "events")
