"""Proof of origin (swarmrec.runtime.origin) with real keys and certificates of the
project's PKI: a robot's signature is accepted only over what it signed, only with its
own certificate, only from the swarm's CA, only while valid; and the statement a fusion
origin signs (swarmrec.wire.fusion.origin_statement) is laid out as documented, built
here by hand."""

from __future__ import annotations

import datetime as dt
import struct
from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import SecurityError
from swarmrec.runtime.origin import OriginSigner, OriginVerifier
from swarmrec.security.identity import Identity
from swarmrec.security.pki import ensure_ca, ensure_identity
from swarmrec.wire import messages as pb
from swarmrec.wire.fusion import origin_statement

SWARM = "proof"


def cn(robot: int) -> str:
    return Identity.service(SWARM, "fusion", robot).common_name


def pki(folder: Path, robots: int = 3, key_type: str = "p256") -> Path:
    ensure_ca(folder, SWARM, key_type=key_type)  # type: ignore[arg-type]
    for r in range(robots):
        ensure_identity(folder, Identity.service(SWARM, "fusion", r), key_type=key_type)  # type: ignore[arg-type]
    return folder


def verifier(folder: Path, ca: Path | None = None) -> OriginVerifier:
    return OriginVerifier(ca or folder / "ca.pem", lambda r: folder / f"{cn(r)}.pem", cn, n_robots=8)


@pytest.mark.parametrize("key_type", ["p256", "ed25519"])
def test_a_robots_signature_is_accepted_over_what_it_signed_only(tmp_path: Path, key_type: str) -> None:
    folder = pki(tmp_path, key_type=key_type)
    check = verifier(folder)
    signature = OriginSigner(folder / f"{cn(1)}.key").sign(b"robot 1 said this")
    assert check.verify(1, b"robot 1 said this", signature) == ""
    assert check.verify(1, b"robot 1 said that", signature) == "the signature is not the origin's"
    # Robot 2's key cannot speak for robot 1, nor robot 1's signature for robot 2.
    forged = OriginSigner(folder / f"{cn(2)}.key").sign(b"robot 1 said this")
    assert check.verify(1, b"robot 1 said this", forged) == "the signature is not the origin's"
    assert check.verify(2, b"robot 1 said this", signature) == "the signature is not the origin's"
    assert check.verify(1, b"robot 1 said this", b"") == "the signature is not the origin's"


def test_a_certificate_of_another_ca_or_name_or_time_is_refused(tmp_path: Path) -> None:
    ours = pki(tmp_path / "ours")
    theirs = pki(tmp_path / "theirs")
    statement = b"said"
    # A certificate with the right name, from another CA, in our folder.
    (ours / f"{cn(2)}.pem").write_bytes((theirs / f"{cn(2)}.pem").read_bytes())
    signed = OriginSigner(theirs / f"{cn(2)}.key").sign(statement)
    assert "not issued by the swarm's CA" in verifier(ours).verify(2, statement, signed)
    # Robot 0's own certificate offered as robot 1's.
    (ours / f"{cn(1)}.pem").write_bytes((ours / f"{cn(0)}.pem").read_bytes())
    signed = OriginSigner(ours / f"{cn(0)}.key").sign(statement)
    assert "not 'r1.fusion.proof'" in verifier(ours).verify(1, statement, signed)
    # No certificate at all; a number that is no robot of the swarm, not even looked for.
    assert "no certificate of robot 7" in verifier(ours).verify(7, statement, signed)
    check = verifier(ours)
    assert check.verify(2**32 - 1, statement, signed) == "robot 4294967295 is not one of the swarm's 8"
    assert check._refused == {}  # nothing kept for it
    # Expired.
    old = dt.datetime.now(dt.UTC) - dt.timedelta(days=30)
    late = tmp_path / "late"
    ensure_ca(late, SWARM, now=old)
    ensure_identity(late, Identity.service(SWARM, "fusion", 0), days=1, now=old)
    signed = OriginSigner(late / f"{cn(0)}.key").sign(statement)
    assert verifier(late).verify(0, statement, signed) == "robot 0's certificate is not valid now"


def test_a_refused_certificate_is_not_read_again_at_once(tmp_path: Path) -> None:
    folder = pki(tmp_path, robots=1)
    check = verifier(folder)
    assert "no certificate of robot 1" in check.verify(1, b"x", b"sig")
    ensure_identity(folder, Identity.service(SWARM, "fusion", 1))
    signed = OriginSigner(folder / f"{cn(1)}.key").sign(b"x")
    # Within RETRY_S the first answer stands; a new verifier reads the file now there.
    assert "no certificate of robot 1" in check.verify(1, b"x", signed)
    assert verifier(folder).verify(1, b"x", signed) == ""


def test_unreadable_keys_and_cas_say_which_file(tmp_path: Path) -> None:
    (tmp_path / "bad.key").write_text("not a key")
    with pytest.raises(SecurityError, match=r"bad\.key"):
        OriginSigner(tmp_path / "bad.key")
    with pytest.raises(SecurityError, match=r"ca\.pem"):
        OriginVerifier(tmp_path / "ca.pem", lambda r: tmp_path, cn, n_robots=1)


def test_the_fusion_statement_is_the_documented_layout() -> None:
    probabilities = np.array([0.25, 0.5, 0.125, 0.125], dtype=np.float32)
    msg = pb.ClassifierOutput(
        origin_robot_id=3,
        round_id=70000,
        probabilities=probabilities.tolist(),
        yaw_rad=-1.5,
        hop_count=2,
        sender_robot_id=1,
        origin_signature=b"whatever",
    )
    expected = (
        b"swarmrec.v1.ClassifierOutput.origin\x00"
        + b"my-swarm\x00"
        + struct.pack("<III", 3, 70000, 4)
        + struct.pack("<4f", 0.25, 0.5, 0.125, 0.125)
        + struct.pack("<f", -1.5)
    )
    assert origin_statement("my-swarm", msg) == expected
    # What relays change is not in it; what the origin said is.
    relayed = pb.ClassifierOutput()
    relayed.CopyFrom(msg)
    relayed.hop_count, relayed.sender_robot_id = 5, 4
    assert origin_statement("my-swarm", relayed) == expected
    for field, value in (("round_id", 70001), ("origin_robot_id", 2), ("yaw_rad", -1.25)):
        changed = pb.ClassifierOutput()
        changed.CopyFrom(msg)
        setattr(changed, field, value)
        assert origin_statement("my-swarm", changed) != expected, field
    assert origin_statement("other-swarm", msg) != expected
