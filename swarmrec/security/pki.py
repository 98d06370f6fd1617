"""The swarm's certificate authority and one certificate per identity.

On disk, one folder per swarm::

    <dir>/ca.pem              the swarm CA's certificate (every node trusts it)
    <dir>/ca.key              the CA's private key (0600; only needed to issue)
    <dir>/<cn>.pem / <cn>.key one pair per identity, named by its common name
    <dir>/acl.json            the router's access control (not secret; rewritten from the settings)

Creation is idempotent: what is missing is created, what is there and right
is kept, and anything there that is not what was asked (another CA, another
name, a key that does not belong to its certificate, a pair cut in half, an
expired certificate) raises :class:`PkiConflictError` unless ``replace`` is
given. Nothing is overwritten silently, because a silently replaced CA would
lock every robot already deployed with the old one out of the swarm.

Keys are EC P-256 by default; Ed25519 is accepted by zenoh's rustls as well
(tests/integration/test_zenoh_mtls.py checks both). The certificates
themselves are built in ``swarmrec.security.certs``.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from swarmrec.errors import ConfigError, PkiConflictError, SecurityError
from swarmrec.runtime.tls import ACL_FILE
from swarmrec.security.acl import access_control
from swarmrec.security.certs import (
    KeyType,
    PrivateKey,
    check_validity,
    common_name_of,
    create_ca,
    issue,
    load_certificate,
    load_private_key,
    now_utc,
    same_public_key,
    sans_of,
    subject_alt_names,
)
from swarmrec.security.identity import SERVICE_KINDS, Identity

__all__ = [
    "DEFAULT_ROUTER_NAMES",
    "CertPaths",
    "Issued",
    "PkiSettings",
    "acl_document",
    "ca_paths",
    "ensure_ca",
    "ensure_identity",
    "identity_paths",
    "init_pki",
    "main",
    "write_acl",
]

Status = Literal["created", "kept", "replaced"]

#: What a client on the router's own host dials; container and k8s names are added per deployment.
DEFAULT_ROUTER_NAMES: tuple[str, ...] = ("localhost", "127.0.0.1", "::1")


@dataclass(frozen=True)
class CertPaths:
    """Where one identity's certificate and private key live."""

    cert: Path
    key: Path


@dataclass(frozen=True)
class Issued:
    """What :func:`ensure_identity` (or :func:`ensure_ca`) did for one name."""

    common_name: str
    paths: CertPaths
    status: Status
    not_after: dt.datetime


def ca_paths(directory: Path) -> CertPaths:
    return CertPaths(directory / "ca.pem", directory / "ca.key")


def identity_paths(directory: Path, identity: Identity) -> CertPaths:
    cn = identity.common_name
    return CertPaths(directory / f"{cn}.pem", directory / f"{cn}.key")


# --- files --------------------------------------------------------------------


def _write(path: Path, data: bytes, mode: int, *, replace: bool) -> None:
    """Write ``data`` to ``path`` with ``mode`` from the first byte on.

    A new file is created with O_EXCL, so a file that appeared meanwhile is
    never clobbered; a replacement goes through a temporary file and an
    atomic rename, so a reader never sees half a key.
    """
    target = path.with_name(path.name + ".tmp") if replace else path
    if replace:
        target.unlink(missing_ok=True)  # left by a run that crashed mid-write
    try:
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise PkiConflictError(target, "appeared while the PKI was being written; not overwritten") from None
    try:
        os.fchmod(fd, mode)  # the umask may have removed bits that a certificate should keep
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    if replace:
        os.replace(target, path)


def _key_pem(key: PrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _save(paths: CertPaths, cert: x509.Certificate, key: PrivateKey, *, replace: bool) -> None:
    # The key first: a crash in between leaves a key without a certificate,
    # which the next run reports, never a certificate whose key is lost.
    _write(paths.key, _key_pem(key), 0o600, replace=replace)
    _write(paths.cert, cert.public_bytes(serialization.Encoding.PEM), 0o644, replace=replace)


def _make_dir(directory: Path) -> None:
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)


def _pair_state(paths: CertPaths) -> Literal["missing", "complete"]:
    have_cert, have_key = paths.cert.exists(), paths.key.exists()
    if have_cert and have_key:
        return "complete"
    if have_cert or have_key:
        present, absent = (paths.cert, paths.key) if have_cert else (paths.key, paths.cert)
        raise PkiConflictError(present, f"exists without {absent.name}; remove it or pass replace")
    return "missing"


def ensure_ca(
    directory: Path,
    swarm: str,
    *,
    key_type: KeyType = "p256",
    days: int = 3650,
    replace: bool = False,
    now: dt.datetime | None = None,
) -> Issued:
    """The swarm CA in ``directory``: created if missing, kept if valid.

    An existing CA is never replaced unless ``replace``: every certificate it
    signed would stop working.
    """
    now = now or now_utc()
    _make_dir(directory)
    paths = ca_paths(directory)
    try:
        if _pair_state(paths) == "complete":
            cert = _check_ca(paths, now)
            return Issued(common_name_of(cert), paths, "kept", cert.not_valid_after_utc)
    except SecurityError:
        if not replace:
            raise
    existed = paths.cert.exists() or paths.key.exists()
    cert, key = create_ca(swarm, key_type=key_type, days=days, now=now)
    _save(paths, cert, key, replace=existed)
    return Issued(common_name_of(cert), paths, "replaced" if existed else "created", cert.not_valid_after_utc)


def _check_ca(paths: CertPaths, now: dt.datetime) -> x509.Certificate:
    cert = load_certificate(paths.cert)
    key = load_private_key(paths.key)
    if not same_public_key(cert, key):
        raise PkiConflictError(paths.key, "is not the key of ca.pem")
    try:
        is_ca = cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    except x509.ExtensionNotFound:
        is_ca = False
    if not is_ca:
        raise PkiConflictError(paths.cert, "is not a CA certificate")
    check_validity(cert, paths.cert, now=now)
    return cert


def ensure_identity(
    directory: Path,
    identity: Identity,
    *,
    sans: Sequence[str] = (),
    key_type: KeyType = "p256",
    days: int = 365,
    renew_within: dt.timedelta = dt.timedelta(0),
    replace: bool = False,
    now: dt.datetime | None = None,
) -> Issued:
    """``identity``'s certificate and key in ``directory``, signed by the CA there.

    Kept when present, signed by this CA, for this CN, holding every SAN in
    ``sans``, matching its key and valid for longer than ``renew_within``;
    otherwise PkiConflictError (or CertificateExpiredError), or a new pair when
    ``replace``. The CA's private key is read only when a certificate is issued.
    """
    now = now or now_utc()
    ca = ca_paths(directory)
    ca_cert = load_certificate(ca.cert)
    paths = identity_paths(directory, identity)
    existed = False
    try:
        existed = _pair_state(paths) == "complete"
        if existed:
            _check_existing(paths, identity, ca_cert, sans, now, renew_within)
            cert = load_certificate(paths.cert)
            return Issued(identity.common_name, paths, "kept", cert.not_valid_after_utc)
    except SecurityError:
        if not replace:
            raise
        existed = True
    ca_key = load_private_key(ca.key)
    if not same_public_key(ca_cert, ca_key):
        raise PkiConflictError(ca.key, "is not the key of ca.pem")
    cert, key = issue(ca_cert, ca_key, identity, sans=sans, key_type=key_type, days=days, now=now)
    _save(paths, cert, key, replace=existed)
    return Issued(identity.common_name, paths, "replaced" if existed else "created", cert.not_valid_after_utc)


def _check_existing(
    paths: CertPaths,
    identity: Identity,
    ca_cert: x509.Certificate,
    sans: Sequence[str],
    now: dt.datetime,
    renew_within: dt.timedelta,
) -> None:
    cert = load_certificate(paths.cert)
    key = load_private_key(paths.key)
    if common_name_of(cert) != identity.common_name:
        raise PkiConflictError(paths.cert, f"is for {common_name_of(cert)!r}, not {identity.common_name!r}")
    if not same_public_key(cert, key):
        raise PkiConflictError(paths.key, f"is not the key of {paths.cert.name}")
    try:
        cert.verify_directly_issued_by(ca_cert)
    except (ValueError, TypeError, InvalidSignature):
        raise PkiConflictError(paths.cert, "was not issued by this directory's ca.pem") from None
    wanted = {str(g.value).lower() for g in subject_alt_names(sans)}
    missing = wanted - sans_of(cert)
    if missing:
        raise PkiConflictError(paths.cert, f"lacks the subject alternative names {sorted(missing)}")
    check_validity(cert, paths.cert, now=now, margin=renew_within)


# --- the `swarmrec pki init` command ------------------------------------------------


@dataclass(frozen=True)
class PkiSettings:
    """What ``swarmrec pki init`` creates: a CA, every robot's services, the
    clients, the operators and the router of one swarm, in ``out``."""

    swarm: str
    robots: int
    out: Path
    kinds: tuple[str, ...] = SERVICE_KINDS
    clients: tuple[str, ...] = ("cli",)
    operators: tuple[str, ...] = ("job",)
    #: Clients that host the gRPC gateway: their certificate also serves its gRPC port.
    gateways: tuple[str, ...] = ("gateway",)
    #: Processes hosting every service of robots first..last (robot or robots:K hosting).
    hosts: tuple[tuple[int, int], ...] = ()
    #: DNS names and IPs the router is dialled at (container or k8s service names too).
    router_names: tuple[str, ...] = DEFAULT_ROUTER_NAMES
    #: DNS names and IPs a gateway's gRPC port is dialled at.
    gateway_names: tuple[str, ...] = (*DEFAULT_ROUTER_NAMES, "gateway")
    #: Every robot also gets a router certificate of its own (r<robot>.router.<swarm>: the
    #: mesh topology, docs/mesh.md), dialled at ``router_names`` like the swarm's router.
    robot_routers: bool = False
    key_type: KeyType = "p256"
    ca_days: int = 3650
    cert_days: int = 365
    #: Certificates that expire within this many days are treated as expired.
    renew_days: int = 0
    #: Replace what does not match (or is expired) instead of stopping; the CA too.
    replace: bool = False
    identities: tuple[Identity, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 1 <= self.robots <= 10_000:
            raise ConfigError(f"robots must be 1..10000, got {self.robots}")
        if not self.kinds or len(set(self.kinds)) != len(self.kinds):
            raise ConfigError(f"kinds must be a non-empty list without repeats, got {self.kinds}")
        if len(set(self.clients)) != len(self.clients) or len(set(self.operators)) != len(self.operators):
            raise ConfigError("client and operator names must not repeat")
        if set(self.gateways) & set(self.clients):
            raise ConfigError("a gateway is a client of its own: do not list it among the clients too")
        if self.key_type not in ("p256", "ed25519"):
            raise ConfigError(f"key type must be p256 or ed25519, got {self.key_type!r}")
        if not 1 <= self.cert_days <= self.ca_days <= 36_500:
            raise ConfigError(
                f"need 1 <= cert_days <= ca_days <= 36500, got {self.cert_days} and {self.ca_days}"
            )
        if not 0 <= self.renew_days < self.cert_days:
            raise ConfigError(f"renew_days must be 0..cert_days-1, got {self.renew_days}")
        if not self.router_names:
            raise ConfigError("the router needs at least one name to be dialled at")
        subject_alt_names(self.router_names)  # raises ConfigError for a bad name
        subject_alt_names(self.gateway_names)
        # Identity validates the swarm name, every kind and every client name.
        ids = [Identity.router(self.swarm)]
        if self.robot_routers:
            ids += [Identity.router(self.swarm, r) for r in range(self.robots)]
        ids += [Identity.service(self.swarm, k, r) for r in range(self.robots) for k in self.kinds]
        for first, last in self.hosts:
            if not 0 <= first <= last < self.robots:
                raise ConfigError(f"a host's robots must be first..last within 0..{self.robots - 1}")
        ids += [Identity.host(self.swarm, first, last) for first, last in self.hosts]
        ids += [Identity.client(self.swarm, n) for n in (*self.clients, *self.gateways)]
        ids += [Identity.operator(self.swarm, n) for n in self.operators]
        object.__setattr__(self, "identities", tuple(ids))


def init_pki(settings: PkiSettings, *, now: dt.datetime | None = None) -> list[Issued]:
    """Create what is missing of ``settings``' PKI; one entry per file pair, CA first."""
    s = settings
    now = now or now_utc()
    out = [ensure_ca(s.out, s.swarm, key_type=s.key_type, days=s.ca_days, replace=s.replace, now=now)]
    for ident in s.identities:
        sans: tuple[str, ...] = ()
        if ident.role == "router":
            sans = s.router_names
        elif ident.role == "client" and ident.name in s.gateways:
            sans = s.gateway_names
        out.append(
            ensure_identity(
                s.out,
                ident,
                sans=sans,
                key_type=s.key_type,
                days=s.cert_days,
                renew_within=dt.timedelta(days=s.renew_days),
                replace=s.replace,
                now=now,
            )
        )
    write_acl(s)
    return out


def acl_document(settings: PkiSettings) -> dict[str, Any]:
    """The router's access control for the identities of ``settings``."""
    s = settings
    return access_control(
        s.swarm,
        s.robots,
        kinds=s.kinds,
        clients=s.clients,
        operators=s.operators,
        gateways=s.gateways,
        hosts=s.hosts,
        robot_routers=s.robot_routers,
    )


def write_acl(settings: PkiSettings) -> Path:
    """``<out>/acl.json``: derived from the settings, not secret, rewritten (atomically) when it
    differs, so a PKI grown by a robot gives the router the robot's rules too."""
    path = settings.out / ACL_FILE
    text = json.dumps(acl_document(settings), indent=1) + "\n"
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    return path


def main(settings: PkiSettings, stdout: TextIO = sys.stdout, *, now: dt.datetime | None = None) -> int:
    """``swarmrec pki init``: create the PKI, print one line per change and a summary.

    Returns 0, or 1 (with the reason on stdout) when an existing file is in
    the way; nothing was overwritten then.
    """
    try:
        done = init_pki(settings, now=now)
    except SecurityError as e:
        print(f"pki: {e}", file=stdout)
        print("pki: nothing was overwritten; fix the file or run again with replace", file=stdout)
        return 1
    for item in done:
        if item.status != "kept":
            print(f"{item.status:8} {item.paths.cert}  (until {item.not_after:%Y-%m-%d})", file=stdout)
    counts = {st: sum(1 for i in done if i.status == st) for st in ("created", "replaced", "kept")}
    print(
        f"pki for swarm {settings.swarm} in {settings.out}: "
        + ", ".join(f"{n} {st}" for st, n in counts.items()),
        file=stdout,
    )
    print(f"pki: keep {ca_paths(settings.out).key} offline once every certificate is issued", file=stdout)
    return 0
