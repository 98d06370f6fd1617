"""Key expressions of the v1 swarm: their layout, the liveliness parser, and
that two swarms sharing a router can never reach each other's keys."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import pytest
import zenoh

from swarmrec.errors import ConfigError
from swarmrec.runtime.keys import (
    CALLER_BOUND,
    alive,
    alive_all,
    bound_caller,
    draining,
    endpoint,
    event,
    parse_alive,
    parse_draining,
    parse_sender,
    request_key,
    validate_swarm_name,
)
from swarmrec.services.registry import kinds

KINDS = kinds()


def test_endpoint_keys_are_swarm_kind_robot_name() -> None:
    assert endpoint("lab", "index-shard", 3, "query") == "swarmrec/v1/lab/index-shard/3/query"
    assert endpoint("lab", "verifier", "*", "verify") == "swarmrec/v1/lab/verifier/*/verify"


def test_a_request_to_a_caller_bound_endpoint_names_its_sender_last() -> None:
    assert ("index-shard", "store") in CALLER_BOUND and ("verifier", "verify") not in CALLER_BOUND
    store = endpoint("lab", "index-shard", 3, "store")
    assert request_key(store, 2) == "swarmrec/v1/lab/index-shard/3/store/2"
    assert request_key(store, "*") == "swarmrec/v1/lab/index-shard/3/store/*"  # for access rules
    assert request_key(store, None) == store  # a client names nobody
    verify = endpoint("lab", "verifier", 3, "verify")
    assert request_key(verify, 2) == verify  # not caller-bound
    assert bound_caller(request_key(store, 2)) == 2
    for key in (
        store,
        f"{store}/x",
        f"{store}/2/3",
        f"{store}/-1",
        f"{store}/{10**11}",
        f"{store}/*",
        f"{store}/²",
    ):
        assert bound_caller(key) is None, key


def test_endpoint_accepts_a_robot_id_given_as_a_digit_string() -> None:
    assert endpoint("lab", "verifier", "7", "verify") == "swarmrec/v1/lab/verifier/7/verify"


def test_endpoint_refuses_a_robot_that_is_neither_an_id_nor_a_wildcard() -> None:
    with pytest.raises(ValueError, match="invalid literal"):
        endpoint("lab", "verifier", "**", "verify")


def test_liveliness_and_event_keys() -> None:
    assert alive("lab", "verifier", 12) == "swarmrec/v1/lab/alive/verifier/12"
    assert alive_all("lab") == "swarmrec/v1/lab/alive/**"
    assert event("lab", "loop-closure", 4) == "swarmrec/v1/lab/events/loop-closure/4"
    assert event("lab", "loop-closure", "*") == "swarmrec/v1/lab/events/loop-closure/*"


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("robot", [0, 9, 4_000_000_000])
def test_parse_alive_reads_back_every_kind_and_robot(kind: str, robot: int) -> None:
    assert parse_alive(alive("lab", kind, robot)) == (kind, robot)


@pytest.mark.parametrize(
    "key",
    [
        "swarmrec/v1/lab/verifier/3/verify",  # an endpoint
        "swarmrec/v1/lab/events/loop-closure/3",  # an event
        "swarmrec/v1/lab/alive/verifier/*",  # a selector, not a token
        "swarmrec/v1/lab/alive/verifier/-1",
        "swarmrec/v1/lab/alive/verifier/3/extra",
        "swarmrec/v1/lab/alive/verifier",
        "swarmrec/v1/lab/alive/verifier/",
        "",
    ],
)
def test_parse_alive_returns_none_for_any_other_key(key: str) -> None:
    assert parse_alive(key) is None


@pytest.mark.parametrize("robot", [0, 9, 4_000_000_000])
def test_parse_draining_reads_back_the_robot(robot: int) -> None:
    assert parse_draining(draining("lab", "index-shard", robot)) == robot


@pytest.mark.parametrize(
    "key",
    [
        "swarmrec/v1/lab/alive/index-shard/3",  # a shard alive is not a shard stopping
        "swarmrec/v1/lab/draining/index-shard/*",
        "swarmrec/v1/lab/draining/index-shard/3/extra",
        "",
    ],
)
def test_parse_draining_returns_none_for_any_other_key(key: str) -> None:
    assert parse_draining(key) is None


@pytest.mark.parametrize("name", ["lab", "a", "A-b_9", "x" * 64])
def test_a_plain_key_segment_is_a_valid_swarm_name(name: str) -> None:
    assert validate_swarm_name(name) == name


@pytest.mark.parametrize(
    "name", ["", "x" * 65, "lab/a", "lab*", "*", "**", "$*", "lab a", "lab?", "lab#", "lab/", "ä", "lab\n"]
)
def test_a_swarm_name_with_anything_but_letters_digits_dash_underscore_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match=r"swarm name must be 1-64 of A-Z a-z 0-9 _ -, got "):
        validate_swarm_name(name)


def every_key(swarm: str) -> list[str]:
    """Every key and selector a swarm's services declare, query or subscribe to."""
    out = [alive_all(swarm)]
    for kind in KINDS:
        for robot in (0, 1, "*"):
            out.append(endpoint(swarm, kind, robot, "query"))
            out.append(event(swarm, "loop-closure", robot))
        out.append(alive(swarm, kind, 0))
    return out


# Names chosen to be prefixes, case variants and near-misses of each other.
SWARMS = ["lab", "lab2", "lab-2", "lab_2", "Lab", "l", "alive", "events", "v1", "swarmrec", "-", "_"]


def test_two_swarm_names_never_produce_intersecting_keys() -> None:
    for a, b in itertools.permutations(SWARMS, 2):
        for ka, kb in itertools.product(every_key(a), every_key(b)):
            assert not zenoh.KeyExpr(ka).intersects(zenoh.KeyExpr(kb)), (ka, kb)


def test_keys_of_one_swarm_reach_each_other() -> None:
    # The check above is not vacuous: the same selectors do match within a swarm.
    k = zenoh.KeyExpr
    assert k(endpoint("lab", "verifier", "*", "query")).includes(k(endpoint("lab", "verifier", 3, "query")))
    assert k(alive_all("lab")).includes(k(alive("lab", "index-shard", 3)))
    assert k(event("lab", "loop-closure", "*")).intersects(k(event("lab", "loop-closure", 2)))


def test_the_compiled_services_bind_the_same_endpoints_to_their_caller() -> None:
    """``runtime::CALLER_BOUND`` in dataplane/src/runtime.rs is the same set."""
    source = (Path(__file__).resolve().parents[2] / "dataplane" / "src" / "runtime.rs").read_text()
    block = source.split("pub const CALLER_BOUND", 1)[1].split("];", 1)[0]
    compiled = set(re.findall(r'\("([a-z-]+)", "([a-z_]+)"\)', block))
    assert compiled == set(CALLER_BOUND)


def test_an_inbox_key_names_its_sender_last() -> None:
    assert parse_sender(endpoint("lab", "fusion", 2, "inbox/3")) == 3
    assert parse_sender(endpoint("lab", "slam", 2, "control/17")) == 17
    for key in (
        endpoint("lab", "fusion", 2, "inbox"),
        "swarmrec/v1/lab/fusion/2/inbox/*",
        "x/1234567",
        "x/²",
    ):
        assert parse_sender(key) is None, key
