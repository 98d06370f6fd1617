"""Install one identity from a folder holding several into the folder a process reads.

On Kubernetes a pod of a StatefulSet cannot mount a Secret of its own: every pod
of the set has the same volumes. The swarm's manifests therefore give each kind
one Secret holding the pairs of every robot of that kind, mount it read-only
into a short init container only, and that container copies the pod's own pair
(and the CA certificate; the router also its ``acl.json``) into a memory volume,
the only one the service's container mounts (docs/kubernetes.md, "Identities").

:func:`install_identity` is that copy. It checks what it copies, so a pod given
the wrong Secret stops here with a message naming the file instead of failing
later as an unreachable router: the certificate is for ``common_name``, it was
issued by the CA beside it, it is valid now, and the key belongs to it. The key
is written 0600 (the runner refuses a key readable by others) and nothing is
ever read or written of the other robots' files.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519

from swarmrec.errors import SecurityError
from swarmrec.runtime.tls import ACL_FILE
from swarmrec.security.certs import common_name_of, load_certificate, same_public_key, verify_issued_by

__all__ = ["install_identity"]


def _copy(source: Path, target: Path, mode: int) -> None:
    """``source``'s bytes into ``target`` with ``mode`` from the first byte (through a
    temporary file and a rename, so a container restarted mid-copy never sees half a key)."""
    data = source.read_bytes()
    tmp = target.with_name(f".{target.name}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.fchmod(fd, mode)  # whatever the umask
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, target)


def install_identity(
    source: Path, target: Path, common_name: str, *, extra: Sequence[str] = (ACL_FILE,)
) -> list[Path]:
    """Copy ``ca.pem`` and ``common_name``'s certificate and key from ``source`` into
    ``target`` (and each of ``extra`` that ``source`` holds, the router's ``acl.json``);
    returns the files written. SecurityError when the pair is missing or is not
    ``common_name``'s, valid and issued by the CA in ``source``."""
    ca, cert, key = source / "ca.pem", source / f"{common_name}.pem", source / f"{common_name}.key"
    for path in (ca, cert, key):
        if not path.is_file():
            raise SecurityError(
                f"{path}: no such file: the Secret mounted at {source} has no identity {common_name} "
                "(create the swarm's Secrets for enough robots: swarmrec k8s secrets --max-robots)"
            )
    ca_cert, own = load_certificate(ca), load_certificate(cert)
    if common_name_of(own) != common_name:
        raise SecurityError(f"{cert}: is for {common_name_of(own)!r}, not {common_name!r}")
    verify_issued_by(own, ca_cert)
    # Read as bytes: a Secret volume gives its files to the pod's group (fsGroup), which the
    # loader's mode check refuses; the copy below is the one the service loads, 0600.
    try:
        private = serialization.load_pem_private_key(key.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as e:
        raise SecurityError(f"{key}: not a readable unencrypted PEM private key ({e})") from None
    if not isinstance(private, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey) or not (
        same_public_key(own, private)
    ):
        raise SecurityError(f"{key}: is not the key of {cert.name}")
    target.mkdir(parents=True, exist_ok=True)
    written = []
    for src, mode in ((ca, 0o444), (cert, 0o444), (key, 0o600)):
        _copy(src, target / src.name, mode)
        written.append(target / src.name)
    for name in extra:
        if (source / name).is_file():
            _copy(source / name, target / name, 0o444)
            written.append(target / name)
    return written
