"""A local run's PKI: its CA's private key lives only as long as the run.

A real local deployment (a real router process under mutual TLS): while it runs, its
PKI folder holds the CA key (a service restarted alone may need a certificate); once
stopped, the key is gone and the certificates stay. The next run in the same folder,
which can no longer issue from that CA, starts a PKI of its own and works.
"""

from __future__ import annotations

from pathlib import Path

from swarmrec.services.settings import PlaceSettings
from tests.integration.conftest import running_swarm


def test_a_stopped_run_leaves_no_ca_key_and_the_next_run_makes_its_own_pki(tmp_path: Path) -> None:
    with running_swarm(tmp_path, "pki-run", PlaceSettings(), robots=2, start=False) as first:
        assert first.pki_dir is not None
        pki = first.pki_dir
        assert (pki / "ca.key").is_file()
        first_ca = (pki / "ca.pem").read_bytes()
    assert not (pki / "ca.key").exists()
    assert (pki / "ca.pem").read_bytes() == first_ca  # the certificates stay with the run
    assert sorted(p.name for p in pki.glob("router.*"))  # the router's pair too
    assert list(tmp_path.rglob("*.key")) != [] and list(tmp_path.rglob("ca.key")) == []

    with running_swarm(tmp_path, "pki-run", PlaceSettings(), robots=2, start=False) as second:
        assert second.pki_dir == pki
        assert (pki / "ca.key").is_file()
        assert (pki / "ca.pem").read_bytes() != first_ca
        # The new router serves the new PKI's client.
        with second.client(role="client") as client:
            assert [(m.kind, m.robot) for m in client.members()] == [("router", 0)]
    assert list(tmp_path.rglob("ca.key")) == []
