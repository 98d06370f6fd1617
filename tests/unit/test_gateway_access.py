"""Who the gateway serves: only its own swarm's clients and operators, by certificate name."""

from __future__ import annotations

import pytest

from swarmrec.security.identity import Identity
from swarmrec.services.gateway import caller_allowed


@pytest.mark.parametrize("identity", [Identity.client("lab", "cli"), Identity.operator("lab", "job")])
def test_this_swarms_clients_and_operators_are_served(identity: Identity) -> None:
    assert caller_allowed(identity.common_name, "lab") == ""


@pytest.mark.parametrize(
    ("common_name", "why"),
    [
        (Identity.service("lab", "verifier", 0).common_name, "is not a client or an operator"),
        (Identity.host("lab", 0, 4).common_name, "is not a client or an operator"),
        (Identity.router("lab").common_name, "is not a client or an operator"),
        (Identity.client("elsewhere", "cli").common_name, "belongs to swarm 'elsewhere', not 'lab'"),
        ("client..lab", "is not a client or an operator"),
        ("client.cli.lab.extra", "is not a client or an operator"),
        ("", "is not a client or an operator"),
    ],
)
def test_anyone_else_is_refused_with_the_reason(common_name: str, why: str) -> None:
    assert why in caller_allowed(common_name, "lab")
