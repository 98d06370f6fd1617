"""What every deployment shares is declared once: the host's numerics settings each container
and pod gets (base.numerics_env), and which kinds get their peers' certificates (the registry's
``peer_certificates``), never a kind's name compared in a deployment."""

from __future__ import annotations

import os
import re

import pytest

from swarmrec.deployments import base, compose, kubernetes
from swarmrec.services import registry
from tests.conftest import REPO


def test_the_openblas_pass_through_is_one_function_every_deployment_calls() -> None:
    assert compose.numerics_env is base.numerics_env
    assert kubernetes.numerics_env is base.numerics_env
    sources = [*(REPO / "swarmrec" / "deployments").glob("*.py"), *(REPO / "swarmrec" / "cli").glob("*.py")]
    assert [p.name for p in sources if 'startswith("OPENBLAS_")' in p.read_text()] == ["base.py"]


def test_the_numerics_settings_are_this_machines_openblas_variables_only_sorted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name in [n for n in os.environ if n.startswith("OPENBLAS_")]:
        monkeypatch.delenv(name)
    assert base.numerics_env() == {}
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    monkeypatch.setenv("SWARMREC_ROBOT", "3")
    monkeypatch.setenv("XOPENBLAS_CORETYPE", "no")
    env = base.numerics_env()
    assert env == {"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_NUM_THREADS": "1"}
    assert list(env) == sorted(env)


def test_the_fusion_entry_alone_checks_its_peers_signatures() -> None:
    assert [k for k, e in registry.REGISTRY.items() if e.peer_certificates] == ["fusion"]


def test_no_deployment_asks_a_kinds_name_whether_it_gets_its_peers_certificates() -> None:
    sources = [*(REPO / "swarmrec" / "deployments").glob("*.py"), REPO / "swarmrec" / "cli" / "k8s.py"]
    for path in sources:
        assert re.search(r"""kind\s*==\s*["']fusion["']""", path.read_text()) is None, path.name
