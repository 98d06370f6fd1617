"""Who each process of a deployed swarm is: the run's PKI and the identities handed out.

Every deployment creates the swarm's PKI for its run (:func:`swarm_pki`: a CA,
one certificate per robot service, the router, the gateway, a read-only
``client.cli`` and the ``operator.job`` that drives replays, and the router's
``acl.json``), gives each service process the settings that name its files
(:func:`security_for`), and connects its own clients as the client or the
operator (:func:`client_tls`). Nothing of it is committed: the PKI lives under
the run's folder. A local run's PKI issues everything at start, and its CA's private key
is removed when the run stops (:func:`retire_ca_key`): what a run leaves behind can sign
nothing. The next run in that folder starts a PKI of its own (:func:`run_pki`).
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import SecuritySettings
from swarmrec.runtime.tls import TlsFiles
from swarmrec.security.identity import SERVICE_KINDS, Identity
from swarmrec.security.pki import DEFAULT_ROUTER_NAMES, PkiSettings, ca_paths, init_pki

__all__ = [
    "CLIENT",
    "OPERATOR",
    "Security",
    "client_tls",
    "retire_ca_key",
    "run_pki",
    "security_for",
    "swarm_pki",
]

Security = Literal["mtls", "insecure"]
Role = Literal["client", "operator"]

#: The names of the read-only client and of the operator every deployment's PKI holds.
CLIENT, OPERATOR = "cli", "job"


def swarm_pki(
    folder: Path,
    swarm: str,
    robots: int,
    *,
    router_names: Sequence[str] = (),
    gateway_names: Sequence[str] = (),
    hosts: Sequence[tuple[int, int]] = (),
    kinds: Sequence[str] = SERVICE_KINDS,
    robot_routers: bool = False,
) -> Path:
    """The PKI of a swarm of ``robots`` in ``folder`` (created, or completed: an existing one
    is kept); the router and the gateway are also dialled at ``router_names`` and
    ``gateway_names`` (a container's host name); ``hosts``: the (first, last) robots of
    each process hosting several services."""
    init_pki(
        PkiSettings(
            swarm=swarm,
            robots=robots,
            out=folder,
            clients=(CLIENT,),
            operators=(OPERATOR,),
            router_names=(*DEFAULT_ROUTER_NAMES, *router_names),
            gateway_names=(*DEFAULT_ROUTER_NAMES, "gateway", *gateway_names),
            hosts=tuple(hosts),
            kinds=tuple(kinds),
            robot_routers=robot_routers,
        )
    )
    return folder


def run_pki(
    folder: Path,
    swarm: str,
    robots: int,
    *,
    hosts: Sequence[tuple[int, int]] = (),
    kinds: Sequence[str] = SERVICE_KINDS,
    robot_routers: bool = False,
) -> Path:
    """The PKI of one local run in ``folder`` (:func:`swarm_pki`). A PKI whose
    CA key an earlier run retired can issue nothing more, and its certificates were that
    run's: it is replaced whole."""
    ca = ca_paths(folder)
    if ca.cert.exists() and not ca.key.exists():
        shutil.rmtree(folder)
    return swarm_pki(folder, swarm, robots, hosts=hosts, kinds=kinds, robot_routers=robot_routers)


def retire_ca_key(folder: Path) -> bool:
    """Remove the CA's private key from a run's PKI once the run is over (its processes
    hold their own certificates; nothing is issued after). Whether there was one."""
    key = ca_paths(folder).key
    if not key.exists():
        return False
    key.unlink()
    return True


def security_for(mode: Security, pki_dir: Path | None, who: str) -> SecuritySettings:
    """The security settings of a deployed process: mutual TLS with the PKI in ``pki_dir``
    (each process's identity is its kind's own), or the explicit insecure mode."""
    if mode == "insecure":
        return SecuritySettings(
            security="insecure", insecure_reason=f"{who} was started with security=insecure"
        )
    if mode != "mtls":
        raise ConfigError(f"security must be mtls or insecure, got {mode!r}")
    if pki_dir is None:
        raise ConfigError("mutual TLS needs the run's PKI folder")
    return SecuritySettings(security="mtls", pki_dir=pki_dir)


def client_tls(pki_dir: Path, swarm: str, role: Role = "operator") -> TlsFiles:
    """The files of the deployment's read-only client or of its operator."""
    ident = Identity.operator(swarm, OPERATOR) if role == "operator" else Identity.client(swarm, CLIENT)
    return TlsFiles.in_dir(pki_dir, ident.common_name)
