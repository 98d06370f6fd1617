"""TLS settings of a zenoh config: mutual TLS on every link, or an explicit,
loudly logged insecure mode.

Checked against eclipse-zenoh 1.10.2 (tests/integration/test_zenoh_mtls.py):

* both ends need ``transport/link/tls/enable_mtls: true``; a client without
  it sends no certificate and the router ends the handshake with
  ``CertificateRequired``;
* ``transport/link/protocols: ["tls"]`` makes a config with a ``tcp/``
  listener fail at ``zenoh.open`` ("Unsupported protocol: tcp"), so the
  router cannot be started with a plaintext door by mistake;
* ``verify_name_on_connect`` checks the router certificate's subject
  alternative names (not its CN) against the host of the ``tls/`` endpoint;
* ``close_link_on_expiration`` drops a link when the peer's certificate
  expires instead of letting it live on.

This module only needs paths and endpoints, so the runner, the deployments
and the tests can all call it; it imports nothing of swarmrec but its errors.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from swarmrec.errors import SecurityError

__all__ = [
    "TlsFiles",
    "configure_client_tls",
    "configure_insecure",
    "configure_router_tls",
    "require_tls_endpoints",
    "tls_endpoint",
]

_TLS = "transport/link/tls"


@dataclass(frozen=True)
class TlsFiles:
    """One node's view of the PKI: the swarm CA it trusts, its own certificate and key."""

    root_ca: Path
    cert: Path
    key: Path

    @classmethod
    def in_dir(cls, directory: Path, common_name: str) -> TlsFiles:
        """The files ``swarmrec.security.pki`` writes for ``common_name`` in ``directory``."""
        return cls(directory / "ca.pem", directory / f"{common_name}.pem", directory / f"{common_name}.key")

    def check(self) -> None:
        """SecurityError when a file is missing or the key is readable by others.

        Zenoh reads the files only when a link opens, and then reports a bad
        path as an unreachable router; checking here names the file instead.
        """
        for path in (self.root_ca, self.cert, self.key):
            if not path.is_file():
                raise SecurityError(f"{path}: no such file (create the PKI with `swarmrec pki init`)")
        mode = self.key.stat().st_mode
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise SecurityError(
                f"{self.key}: private key is accessible to group or others (mode {mode & 0o777:o})"
            )


def tls_endpoint(host: str, port: int) -> str:
    """``tls/<host>:<port>``, with an IPv6 address in brackets."""
    try:
        if ipaddress.ip_address(host).version == 6:
            host = f"[{host}]"
    except ValueError:
        pass  # a DNS name: the router certificate must carry it as a SAN
    return f"tls/{host}:{port}"


def require_tls_endpoints(endpoints: Sequence[str]) -> tuple[str, ...]:
    """``endpoints`` if every one is ``tls/...``, else SecurityError naming the others."""
    if not endpoints:
        raise SecurityError("no endpoint given")
    plain = [e for e in endpoints if not e.startswith("tls/")]
    if plain:
        raise SecurityError(f"endpoints {plain} are not tls/: mutual TLS is on, plaintext links are refused")
    return tuple(endpoints)


def _insert(conf: zenoh.Config, key: str, value: object) -> None:
    conf.insert_json5(key, json.dumps(value))


def _common(conf: zenoh.Config, files: TlsFiles) -> None:
    files.check()
    _insert(conf, f"{_TLS}/root_ca_certificate", str(files.root_ca))
    _insert(conf, f"{_TLS}/enable_mtls", True)
    _insert(conf, f"{_TLS}/close_link_on_expiration", True)
    # The whitelist applies to accepting and opening: no tcp/udp/ws link can exist.
    _insert(conf, "transport/link/protocols", ["tls"])


def configure_router_tls(conf: zenoh.Config, files: TlsFiles, listen: Sequence[str]) -> None:
    """Make ``conf`` (a router's) listen on ``listen`` with mutual TLS only.

    Every connecting node must present a certificate signed by ``files.root_ca``.
    The router's own certificate doubles as its client certificate, so a
    router that also connects to another router does so with mutual TLS.
    """
    _insert(conf, "listen/endpoints", list(require_tls_endpoints(listen)))
    _common(conf, files)
    _insert(conf, f"{_TLS}/listen_certificate", str(files.cert))
    _insert(conf, f"{_TLS}/listen_private_key", str(files.key))
    _insert(conf, f"{_TLS}/connect_certificate", str(files.cert))
    _insert(conf, f"{_TLS}/connect_private_key", str(files.key))
    _insert(conf, f"{_TLS}/verify_name_on_connect", True)


def configure_client_tls(conf: zenoh.Config, files: TlsFiles, connect: Sequence[str]) -> None:
    """Make ``conf`` (a client's or a peer's) connect to ``connect`` with mutual TLS only.

    The router's certificate must be signed by ``files.root_ca`` and name the
    endpoint's host among its subject alternative names.
    """
    _insert(conf, "connect/endpoints", list(require_tls_endpoints(connect)))
    _common(conf, files)
    _insert(conf, f"{_TLS}/connect_certificate", str(files.cert))
    _insert(conf, f"{_TLS}/connect_private_key", str(files.key))
    _insert(conf, f"{_TLS}/verify_name_on_connect", True)


def configure_insecure(conf: zenoh.Config, log: logging.Logger, *, who: str, reason: str) -> None:
    """Leave ``conf``'s links plaintext and unauthenticated, and say so loudly.

    For debugging only (a packet capture, a laptop without the PKI). It needs
    a ``reason`` so the choice is always explicit and always in the log; it
    refuses a config that already holds TLS settings, since half a TLS setup
    is worse than either.
    """
    if not reason.strip():
        raise SecurityError("the insecure mode needs a reason; it is never the silent default")
    if conf.get_json(f"{_TLS}/enable_mtls") not in ("null", "false"):
        raise SecurityError(f"{who}: mutual TLS is already configured; refusing to mix it with insecure mode")
    log.warning(
        "INSECURE MODE: %s uses plaintext, unauthenticated zenoh links. Anyone who can reach its "
        "endpoints can read every message, impersonate any robot and store into any index. "
        "Reason given: %s. Never run a swarm like this outside a closed lab network.",
        who,
        reason,
        extra={"fields": {"security": "insecure", "reason": reason}},
    )
