"""A caller's keys declared to the router (:class:`DeclaredKeys`): once each, at most
``limit`` of them, and the plain string where zenoh refuses (the request then behaves as
it did before declarations)."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
import zenoh

from swarmrec.runtime.rpc import Caller, DeclaredKeys


def _session() -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    return zenoh.open(conf)


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    with _session() as s:
        yield s


def test_a_key_is_declared_once_and_the_same_declaration_serves_every_request(session: zenoh.Session) -> None:
    keys = DeclaredKeys(session)
    first = keys("swarmrec/v1/t/index-shard/3/query")
    assert isinstance(first, zenoh.KeyExpr) and str(first) == "swarmrec/v1/t/index-shard/3/query"
    assert keys("swarmrec/v1/t/index-shard/3/query") is first
    assert len(keys) == 1


def test_past_the_limit_keys_go_as_strings(session: zenoh.Session) -> None:
    keys = DeclaredKeys(session, limit=2)
    assert isinstance(keys("a/1"), zenoh.KeyExpr) and isinstance(keys("a/2"), zenoh.KeyExpr)
    assert keys("a/3") == "a/3"
    assert len(keys) == 2
    assert isinstance(keys("a/1"), zenoh.KeyExpr)  # the declared ones stay declared


def test_a_string_zenoh_refuses_or_a_closed_session_gives_the_string_back() -> None:
    s = _session()
    keys = DeclaredKeys(s)
    assert keys("not//a key") == "not//a key"  # `get` refuses it as before
    s.close()
    assert keys("a/b") == "a/b"
    assert len(keys) == 0


def test_callers_made_per_request_share_their_services_declarations(session: zenoh.Session) -> None:
    service = Caller(session, 0)
    assert isinstance(service.keys, DeclaredKeys)
    per_call = Caller(session, None, keys=service.keys)
    assert per_call.keys is service.keys
    assert Caller(session, 1).keys is not service.keys
