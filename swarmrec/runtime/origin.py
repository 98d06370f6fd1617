"""Proof of origin: what a robot says as itself, signed with its certificate's key and
checked by any other robot against the swarm's CA.

The router's access control ties each message to the certificate of the robot that
*sent* it (the key names the sender). A relayed message also names an *origin*, which
only a signature can vouch for: the origin signs a statement of what it said (the
bytes are the caller's, e.g. :func:`swarmrec.wire.fusion.origin_statement`) with the
private key of its service's certificate, and a receiver checks the signature with
the public key of the origin's certificate, which it accepts only when the swarm's CA
issued it, it is valid now, and its common name is the origin's (``expected_cn``).

Keys are the PKI's (``swarmrec.security.certs``): ECDSA P-256 with SHA-256 (a DER
signature of 70 to 72 bytes) or Ed25519 (64 bytes). Certificates are read from the
PKI folder once per robot and kept; one that does not pass is read again at most
every :data:`RETRY_S`, so a refused certificate costs no repeated work.
"""

from __future__ import annotations

import datetime as dt
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import NameOID

from swarmrec.errors import SecurityError

__all__ = ["RETRY_S", "OriginSigner", "OriginVerifier", "PrivateKey", "load_private_key"]

#: How often a robot's certificate that did not pass (missing, foreign, expired) is read again.
RETRY_S = 10.0

PrivateKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey


def load_private_key(path: Path) -> PrivateKey:
    """The PKI's private key in ``path`` (unencrypted PEM, ECDSA or Ed25519, readable by its
    owner only); SecurityError saying which file and why otherwise."""
    mode = path.stat().st_mode
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SecurityError(f"{path}: private key is accessible to group or others (mode {mode & 0o777:o})")
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as e:
        raise SecurityError(f"{path}: not a readable unencrypted PEM private key ({e})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey):
        raise SecurityError(f"{path}: key type {type(key).__name__} is not EC or Ed25519")
    return key


class OriginSigner:
    """Signs statements with one private key (a PEM file of the PKI)."""

    def __init__(self, key_path: Path) -> None:
        try:
            self._key = load_private_key(key_path)
        except OSError as e:  # no such file: said as every other unreadable key
            raise SecurityError(f"{key_path}: cannot read the signing key: {e}") from e

    def sign(self, statement: bytes) -> bytes:
        if isinstance(self._key, ec.EllipticCurvePrivateKey):
            return self._key.sign(statement, ec.ECDSA(hashes.SHA256()))
        return self._key.sign(statement)


class OriginVerifier:
    """Checks robots' signatures against their certificates, issued by the swarm's CA.

    ``cert_path(robot)`` is where robot ``robot``'s certificate is, ``expected_cn(robot)``
    the common name it must carry; robots are numbered below ``n_robots`` (another number
    is refused at once, and never remembered: what is kept is bounded by the swarm). Safe
    to call from several threads."""

    def __init__(
        self,
        ca_path: Path,
        cert_path: Callable[[int], Path],
        expected_cn: Callable[[int], str],
        *,
        n_robots: int,
    ) -> None:
        try:
            self._ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
        except (OSError, ValueError) as e:
            raise SecurityError(f"{ca_path}: cannot read the CA certificate: {e}") from e
        self._cert_path, self._expected_cn, self._n_robots = cert_path, expected_cn, n_robots
        self._keys: dict[int, Any] = {}
        self._refused: dict[int, tuple[float, str]] = {}  # robot -> (when, why)
        self._lock = threading.Lock()

    def verify(self, robot: int, statement: bytes, signature: bytes) -> str:
        """An empty string when ``signature`` is robot ``robot``'s over ``statement``; else why not."""
        if not 0 <= robot < self._n_robots:
            return f"robot {robot} is not one of the swarm's {self._n_robots}"
        key = self._key_of(robot)
        if isinstance(key, str):
            return key
        try:
            if isinstance(key, ec.EllipticCurvePublicKey):
                key.verify(signature, statement, ec.ECDSA(hashes.SHA256()))
            else:
                key.verify(signature, statement)
        except InvalidSignature:
            return "the signature is not the origin's"
        return ""

    def _key_of(self, robot: int) -> Any:
        """Robot ``robot``'s public key, or why there is none."""
        with self._lock:
            if robot in self._keys:
                return self._keys[robot]
            refused = self._refused.get(robot)
            if refused is not None and time.monotonic() - refused[0] < RETRY_S:
                return refused[1]
            why = ""
            try:
                key = self._load(robot)
            except SecurityError as e:
                why = str(e)
            if why:
                self._refused[robot] = (time.monotonic(), why)
                return why
            self._refused.pop(robot, None)
            self._keys[robot] = key
            return key

    def _load(self, robot: int) -> Any:
        path = self._cert_path(robot)
        try:
            cert = x509.load_pem_x509_certificate(path.read_bytes())
        except (OSError, ValueError) as e:
            raise SecurityError(f"no certificate of robot {robot} ({path}): {e}") from e
        try:
            cert.verify_directly_issued_by(self._ca)
        except (ValueError, TypeError, InvalidSignature) as e:
            raise SecurityError(f"robot {robot}'s certificate is not issued by the swarm's CA") from e
        now = dt.datetime.now(dt.UTC)
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            raise SecurityError(f"robot {robot}'s certificate is not valid now")
        names = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
        expected = self._expected_cn(robot)
        if names != [expected]:
            raise SecurityError(f"robot {robot}'s certificate names {names}, not {expected!r}")
        key = cert.public_key()
        if not isinstance(key, ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey):
            raise SecurityError(
                f"robot {robot}'s certificate has a {type(key).__name__}, not ECDSA or Ed25519"
            )
        return key
