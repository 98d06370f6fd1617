"""X.509 for the swarm, in memory: the CA, end certificates, and their checks.

Pure functions of keys and certificates (``swarmrec.security.pki`` puts them
on disk). Every end certificate carries its identity's common name
(swarmrec.security.identity), both serverAuth and clientAuth, and the
subject alternative names a peer dials it by.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from swarmrec.errors import CertificateExpiredError, ConfigError, SecurityError
from swarmrec.runtime.origin import PrivateKey, load_private_key
from swarmrec.security.identity import Identity

__all__ = [
    "KeyType",
    "PrivateKey",
    "check_validity",
    "common_name_of",
    "create_ca",
    "issue",
    "load_certificate",
    "load_private_key",
    "new_key",
    "now_utc",
    "same_public_key",
    "sans_of",
    "subject_alt_names",
    "verify_issued_by",
]

KeyType = Literal["p256", "ed25519"]

# Certificates start a little in the past: a robot whose clock is a few
# minutes behind the machine that issued its certificate must still accept it.
_BACKDATE = dt.timedelta(minutes=5)
_DNS_LABEL = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)$")
_ORG = "swarmrec"


def now_utc() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def new_key(key_type: KeyType) -> PrivateKey:
    if key_type == "p256":
        return ec.generate_private_key(ec.SECP256R1())
    if key_type == "ed25519":
        return ed25519.Ed25519PrivateKey.generate()
    raise ConfigError(f"key type must be p256 or ed25519, got {key_type!r}")


def _sign_hash(key: PrivateKey) -> hashes.SHA256 | None:
    # Ed25519 signs the message itself; X.509 forbids naming a digest for it.
    return None if isinstance(key, ed25519.Ed25519PrivateKey) else hashes.SHA256()


def subject_alt_names(names: Sequence[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for name in names:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(name)))
            continue
        except ValueError:
            pass
        labels = name.rstrip(".").split(".")
        if len(name) > 253 or not all(_DNS_LABEL.fullmatch(label) for label in labels):
            raise ConfigError(f"subject alternative name {name!r} is neither an IP address nor a DNS name")
        out.append(x509.DNSName(name.rstrip(".").lower()))
    return out


def create_ca(
    swarm: str, *, key_type: KeyType = "p256", days: int = 3650, now: dt.datetime | None = None
) -> tuple[x509.Certificate, PrivateKey]:
    """A new self-signed CA for ``swarm`` (in memory; :func:`ensure_ca` writes it)."""
    now = now or now_utc()
    key = new_key(key_type)
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG),
            x509.NameAttribute(NameOID.COMMON_NAME, f"swarmrec CA {swarm}"),
        ]
    )
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _BACKDATE)
        .not_valid_after(now + dt.timedelta(days=days))
        # path_length 0: the CA signs only end certificates, never another CA.
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(ski, critical=False)
        .sign(key, _sign_hash(key))
    )
    return cert, key


def issue(
    ca_cert: x509.Certificate,
    ca_key: PrivateKey,
    identity: Identity,
    *,
    sans: Sequence[str] = (),
    key_type: KeyType = "p256",
    days: int = 365,
    now: dt.datetime | None = None,
) -> tuple[x509.Certificate, PrivateKey]:
    """A certificate for ``identity`` signed by the CA (in memory).

    Every certificate may both serve and connect (serverAuth and clientAuth):
    a router listens and may connect to another router, a service connects and
    may one day listen as a peer. ``sans`` are the DNS names and IPs a peer
    dials to reach it; the router needs them for name verification, a
    service or client needs none (mTLS checks a client's chain, not its name).
    """
    now = now or now_utc()
    key = new_key(key_type)
    not_after = min(now + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    builder = (
        x509.CertificateBuilder()
        .subject_name(
            x509.Name(
                [
                    x509.NameAttribute(NameOID.ORGANIZATION_NAME, _ORG),
                    x509.NameAttribute(NameOID.COMMON_NAME, identity.common_name),
                ]
            )
        )
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _BACKDATE)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
    )
    if sans:
        builder = builder.add_extension(x509.SubjectAlternativeName(subject_alt_names(sans)), critical=False)
    return builder.sign(ca_key, _sign_hash(ca_key)), key


def load_certificate(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as e:
        raise SecurityError(f"{path}: not a readable PEM certificate ({e})") from None


def check_validity(
    cert: x509.Certificate,
    path: Path | str = "<certificate>",
    *,
    now: dt.datetime | None = None,
    margin: dt.timedelta = dt.timedelta(0),
) -> dt.timedelta:
    """Time left before ``cert`` expires; CertificateExpiredError when it is
    outside its validity, or will be within ``margin``."""
    now = now or now_utc()
    start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
    if now < start or now + margin >= end:
        raise CertificateExpiredError(path, start.isoformat(), end.isoformat())
    return end - now


def verify_issued_by(
    cert: x509.Certificate, ca_cert: x509.Certificate, *, now: dt.datetime | None = None
) -> None:
    """SecurityError unless ``ca_cert`` signed ``cert`` and both are valid now."""
    try:
        cert.verify_directly_issued_by(ca_cert)
    except (ValueError, TypeError, InvalidSignature) as e:
        reason = str(e) or type(e).__name__
        raise SecurityError(
            f"{common_name_of(cert)} was not issued by {common_name_of(ca_cert)}: {reason}"
        ) from None
    check_validity(ca_cert, common_name_of(ca_cert), now=now)
    check_validity(cert, common_name_of(cert), now=now)


def common_name_of(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else ""
    return value if isinstance(value, str) else value.decode()


def sans_of(cert: x509.Certificate) -> set[str]:
    try:
        ext = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return set()
    return {n.lower() for n in ext.get_values_for_type(x509.DNSName)} | {
        str(ip) for ip in ext.get_values_for_type(x509.IPAddress)
    }


def same_public_key(cert: x509.Certificate, key: PrivateKey) -> bool:
    der = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    return cert.public_key().public_bytes(*der) == key.public_key().public_bytes(*der)
