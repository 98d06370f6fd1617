"""The swarm PKI: the common-name scheme, what each certificate holds, files
and their modes, idempotence, refusals to overwrite, expiry, and that a
certificate of another CA fails verification (checked by cryptography itself)."""

from __future__ import annotations

import datetime as dt
import io
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

import swarmrec.security as security
from swarmrec.errors import CertificateExpiredError, ConfigError, PkiConflictError, SecurityError
from swarmrec.security.certs import check_validity, create_ca, issue, load_certificate, verify_issued_by
from swarmrec.security.identity import SERVICE_KINDS, Identity, parse_common_name
from swarmrec.security.pki import (
    PkiSettings,
    ca_paths,
    ensure_ca,
    ensure_identity,
    identity_paths,
    init_pki,
    main,
)

SWARM = "lab"
NOW = dt.datetime(2030, 1, 1, tzinfo=dt.UTC)


@pytest.fixture
def pki(tmp_path: Path) -> Path:
    out = tmp_path / "pki"
    init_pki(PkiSettings(swarm=SWARM, robots=2, out=out), now=NOW)
    return out


@pytest.fixture
def open_umask() -> Iterator[None]:
    """A umask that lets everybody read new files, as on a careless machine."""
    old = os.umask(0)
    try:
        yield
    finally:
        os.umask(old)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def cn_of(cert: x509.Certificate) -> str:
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def sans_of(cert: x509.Certificate) -> list[str]:
    ext = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return [str(v) for v in ext.get_values_for_type(x509.DNSName)] + [
        str(v) for v in ext.get_values_for_type(x509.IPAddress)
    ]


# --- the common-name scheme ------------------------------------------------------


def test_common_names_name_robot_kind_and_swarm() -> None:
    assert Identity.service(SWARM, "index-shard", 3).common_name == "r3.index-shard.lab"
    assert Identity.client(SWARM, "cli").common_name == "client.cli.lab"
    assert Identity.operator(SWARM, "job").common_name == "operator.job.lab"
    assert Identity.router(SWARM).common_name == "router.lab"
    assert Identity.host(SWARM, 3).common_name == "r3.host.lab"
    assert Identity.host(SWARM, 0, 4).common_name == "r0-4.host.lab"
    assert list(Identity.host(SWARM, 0, 4).robots) == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    "identity",
    [
        *(Identity.service("s_1-x", kind, 12) for kind in SERVICE_KINDS),
        Identity.client("s", "cli-2"),
        Identity.operator("s", "job"),
        Identity.router("s"),
        Identity.router("s", 3),
        Identity.host("s", 7),
        Identity.host("s", 10, 19),
    ],
)
def test_every_common_name_parses_back_to_its_identity(identity: Identity) -> None:
    assert parse_common_name(identity.common_name) == identity


def test_a_robots_own_router_is_a_router_that_acts_for_no_robot() -> None:
    # The mesh (docs/mesh.md): robot 3's router relays, it is none of robot 3's services.
    ident = parse_common_name("r3.router.lab")
    assert (ident.role, ident.robot, ident.kind) == ("router", 3, "")
    assert list(ident.robots) == []
    assert Identity.router("lab").common_name == "router.lab"


@pytest.mark.parametrize(
    "cn",
    [
        "r03.router.lab",  # one spelling per robot id, a robot's own router's too
        "r03.verifier.lab",  # one spelling per robot id
        "r-1.verifier.lab",
        "r3.verifier.lab.extra",
        "client.Cli.lab",
        "client.a.b.lab",
        "client..lab",
        "router.lab.x",
        "verifier.3.lab",
        "r3.verifier.la*b",
        "r3-1.host.lab",  # a host's robots run first..last
        "r03-4.host.lab",
        "r3-4.verifier.lab",  # only a host spans robots
    ],
)
def test_names_outside_the_scheme_are_refused(cn: str) -> None:
    with pytest.raises(ConfigError):
        parse_common_name(cn)


def test_an_identity_refuses_fields_of_another_role() -> None:
    with pytest.raises(ConfigError, match="no name"):
        Identity(SWARM, "service", kind="verifier", robot=1, name="x")
    with pytest.raises(ConfigError, match="name, not a kind"):
        Identity(SWARM, "client", kind="verifier", name="x")
    with pytest.raises(ConfigError, match="swarm name"):
        Identity.router("a.b")
    with pytest.raises(ConfigError, match=r"first\.\.last"):
        Identity.host(SWARM, 4, 3)
    with pytest.raises(ConfigError, match="only its robots"):
        Identity(SWARM, "host", kind="verifier", robot=1, last=1)


def test_a_host_is_granted_exactly_what_its_robots_services_are() -> None:
    from swarmrec.security.acl import grants

    robots = range(6)
    host = grants(Identity.host(SWARM, 2, 3), robots)
    services = [
        g for r in (2, 3) for k in SERVICE_KINDS for g in grants(Identity.service(SWARM, k, r), robots)[1:]
    ]
    assert host[1:] == services
    keys_granted = {k for g in host if g.flow == "ingress" for k in g.key_exprs}
    assert any("/verifier/2/" in k for k in keys_granted) and any("/verifier/3/" in k for k in keys_granted)
    assert not any("/verifier/1/" in k or "/verifier/4/" in k for k in keys_granted if "store" not in k)


def test_pki_init_issues_the_host_certificates_asked_for_and_the_acl_names_them(tmp_path: Path) -> None:
    import json

    out = tmp_path / "pki"
    init_pki(PkiSettings(swarm=SWARM, robots=4, out=out, hosts=((0, 1), (2, 3), (2, 2))))
    assert {p.name for p in out.glob("r*.host.*.pem")} == {
        "r0-1.host.lab.pem",
        "r2-3.host.lab.pem",
        "r2.host.lab.pem",
    }
    acl = json.loads((out / "acl.json").read_text())
    assert {"r0-1.host.lab", "r2-3.host.lab", "r2.host.lab"} <= {s["id"] for s in acl["subjects"]}
    with pytest.raises(ConfigError, match="host's robots"):
        PkiSettings(swarm=SWARM, robots=4, out=out, hosts=((3, 4),))


# --- what the certificates hold ---------------------------------------------------


def test_the_ca_is_a_self_signed_ca_that_signs_only_end_certificates(pki: Path) -> None:
    ca = load_certificate(ca_paths(pki).cert)
    assert ca.subject == ca.issuer
    ca.verify_directly_issued_by(ca)
    basic = ca.extensions.get_extension_for_class(x509.BasicConstraints)
    assert basic.critical and basic.value.ca and basic.value.path_length == 0
    usage = ca.extensions.get_extension_for_class(x509.KeyUsage).value
    assert usage.key_cert_sign and usage.crl_sign and not usage.digital_signature
    assert ca.not_valid_after_utc - NOW == dt.timedelta(days=3650)


def test_a_service_certificate_names_its_robot_and_kind_and_may_serve_and_connect(pki: Path) -> None:
    ident = Identity.service(SWARM, "verifier", 1)
    cert = load_certificate(identity_paths(pki, ident).cert)
    ca = load_certificate(ca_paths(pki).cert)
    assert cn_of(cert) == "r1.verifier.lab"
    assert cert.issuer == ca.subject
    verify_issued_by(cert, ca, now=NOW)
    assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    usage = cert.extensions.get_extension_for_class(x509.KeyUsage)
    assert usage.critical and usage.value.digital_signature and not usage.value.key_cert_sign
    eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    # mTLS checks a client's chain, not a name: services carry no SAN.
    with pytest.raises(x509.ExtensionNotFound):
        cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert isinstance(cert.public_key(), ec.EllipticCurvePublicKey)
    assert cert.public_key().curve.name == "secp256r1"  # type: ignore[union-attr]  # narrowed by the assert above
    assert cert.not_valid_after_utc - NOW == dt.timedelta(days=365)


def test_the_router_certificate_carries_the_names_it_is_dialled_at(tmp_path: Path) -> None:
    names = ("localhost", "127.0.0.1", "::1", "router", "swarmrec-router.lab.svc.cluster.local")
    init_pki(PkiSettings(swarm=SWARM, robots=1, out=tmp_path, router_names=names), now=NOW)
    cert = load_certificate(identity_paths(tmp_path, Identity.router(SWARM)).cert)
    assert cn_of(cert) == "router.lab"
    assert sorted(sans_of(cert)) == sorted(names)


def test_pki_init_creates_one_pair_per_identity_in_the_documented_layout(pki: Path) -> None:
    expected = {"ca.pem", "ca.key", "router.lab.pem", "router.lab.key"}
    expected |= {f"client.cli.lab.{x}" for x in ("pem", "key")}
    expected |= {f"operator.job.lab.{x}" for x in ("pem", "key")}
    expected |= {f"client.gateway.lab.{x}" for x in ("pem", "key")} | {"acl.json"}
    expected |= {f"r{r}.{k}.lab.{x}" for r in range(2) for k in SERVICE_KINDS for x in ("pem", "key")}
    assert {p.name for p in pki.iterdir()} == expected


def test_ed25519_keys_can_be_chosen(tmp_path: Path) -> None:
    init_pki(PkiSettings(swarm=SWARM, robots=1, out=tmp_path, key_type="ed25519"), now=NOW)
    ca = load_certificate(ca_paths(tmp_path).cert)
    cert = load_certificate(identity_paths(tmp_path, Identity.service(SWARM, "detector", 0)).cert)
    assert isinstance(ca.public_key(), ed25519.Ed25519PublicKey)
    assert isinstance(cert.public_key(), ed25519.Ed25519PublicKey)
    verify_issued_by(cert, ca, now=NOW)


def test_a_certificate_never_outlives_its_ca() -> None:
    ca, ca_key = create_ca(SWARM, days=10, now=NOW)
    cert, _ = issue(ca, ca_key, Identity.client(SWARM, "cli"), days=365, now=NOW)
    assert cert.not_valid_after_utc == ca.not_valid_after_utc


def test_a_bad_subject_alternative_name_is_refused() -> None:
    ca, ca_key = create_ca(SWARM, now=NOW)
    with pytest.raises(ConfigError, match="neither an IP address nor a DNS name"):
        issue(ca, ca_key, Identity.router(SWARM), sans=["under_score.example"], now=NOW)


# --- another CA -------------------------------------------------------------------


def test_a_certificate_from_another_ca_fails_verification(pki: Path, tmp_path: Path) -> None:
    ours = load_certificate(ca_paths(pki).cert)
    # The impostor CA copies our CA's name exactly; only its key differs.
    other, other_key = create_ca(SWARM, now=NOW)
    assert other.subject == ours.subject
    forged, _ = issue(other, other_key, Identity.service(SWARM, "verifier", 1), now=NOW)
    with pytest.raises(SecurityError, match="was not issued by"):
        verify_issued_by(forged, ours, now=NOW)
    verify_issued_by(forged, other, now=NOW)  # the control: it is a sound certificate of its own CA


def test_a_pair_signed_by_another_ca_is_not_kept(pki: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    init_pki(PkiSettings(swarm=SWARM, robots=2, out=other), now=NOW)
    ident = Identity.service(SWARM, "verifier", 1)
    theirs = identity_paths(other, ident)
    ours = identity_paths(pki, ident)
    ours.cert.write_bytes(theirs.cert.read_bytes())
    ours.key.write_bytes(theirs.key.read_bytes())
    with pytest.raises(PkiConflictError, match=r"r1\.verifier\.lab\.pem: was not issued by this directory"):
        ensure_identity(pki, ident, now=NOW)


# --- files, modes, idempotence ----------------------------------------------------


@pytest.mark.usefixtures("open_umask")
def test_private_keys_are_0600_and_the_folder_0700_whatever_the_umask(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    init_pki(PkiSettings(swarm=SWARM, robots=1, out=out), now=NOW)
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    keys = list(out.glob("*.key"))
    assert len(keys) == 1 + 1 + len(SERVICE_KINDS) + 3  # CA, router, services, client, operator, gateway
    for path in keys:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    for path in out.glob("*.pem"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o644, path


def test_running_init_again_keeps_every_file_byte_for_byte(pki: Path) -> None:
    before = snapshot(pki)
    done = init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki), now=NOW + dt.timedelta(days=1))
    assert {d.status for d in done} == {"kept"}
    assert snapshot(pki) == before


def test_init_creates_only_what_is_missing(pki: Path) -> None:
    before = snapshot(pki)
    done = init_pki(PkiSettings(swarm=SWARM, robots=3, out=pki, clients=("cli", "viewer")), now=NOW)
    created = {d.common_name for d in done if d.status == "created"}
    assert created == {f"r2.{k}.lab" for k in SERVICE_KINDS} | {"client.viewer.lab"}
    after = snapshot(pki)
    # Every certificate and key stays byte for byte; acl.json (derived, not secret) grows.
    kept = {k: v for k, v in before.items() if k != "acl.json"}
    assert {k: after[k] for k in kept} == kept
    assert b"r2.verifier.lab" in after["acl.json"] and b"client.viewer.lab" in after["acl.json"]


def test_a_key_without_its_certificate_is_reported_not_replaced(pki: Path) -> None:
    paths = identity_paths(pki, Identity.client(SWARM, "cli"))
    paths.cert.unlink()
    key = paths.key.read_bytes()
    with pytest.raises(PkiConflictError, match=r"client\.cli\.lab\.key: exists without client\.cli"):
        init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki), now=NOW)
    assert paths.key.read_bytes() == key and not paths.cert.exists()


def test_a_certificate_for_another_name_is_reported_not_replaced(pki: Path) -> None:
    a = identity_paths(pki, Identity.service(SWARM, "verifier", 0))
    b = identity_paths(pki, Identity.service(SWARM, "verifier", 1))
    a.cert.write_bytes(b.cert.read_bytes())
    a.key.write_bytes(b.key.read_bytes())
    with pytest.raises(PkiConflictError, match=r"is for 'r1\.verifier\.lab', not 'r0\.verifier\.lab'"):
        ensure_identity(pki, Identity.service(SWARM, "verifier", 0), now=NOW)


def test_a_key_that_does_not_belong_to_its_certificate_is_reported(pki: Path) -> None:
    a = identity_paths(pki, Identity.service(SWARM, "verifier", 0))
    b = identity_paths(pki, Identity.service(SWARM, "verifier", 1))
    a.key.write_bytes(b.key.read_bytes())
    with pytest.raises(PkiConflictError, match=r"r0\.verifier\.lab\.key: is not the key of"):
        ensure_identity(pki, Identity.service(SWARM, "verifier", 0), now=NOW)


def test_a_router_certificate_missing_a_requested_name_is_reported(pki: Path) -> None:
    with pytest.raises(PkiConflictError, match=r"lacks the subject alternative names \['router'\]"):
        init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki, router_names=("localhost", "router")), now=NOW)


def test_a_new_ca_never_silently_replaces_the_old_one(pki: Path) -> None:
    ca = ca_paths(pki)
    ca.key.write_bytes(b"not a key")
    ca.key.chmod(0o600)
    with pytest.raises(SecurityError, match=r"ca\.key: not a readable unencrypted PEM private key"):
        ensure_ca(pki, SWARM, now=NOW)


def test_replace_reissues_everything_under_a_new_ca_and_old_certificates_stop_verifying(pki: Path) -> None:
    old_ca = load_certificate(ca_paths(pki).cert)
    ca_paths(pki).key.unlink()
    done = init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki, replace=True), now=NOW)
    assert {d.status for d in done} == {"replaced"}
    new_ca = load_certificate(ca_paths(pki).cert)
    cert = load_certificate(identity_paths(pki, Identity.service(SWARM, "fusion", 1)).cert)
    verify_issued_by(cert, new_ca, now=NOW)
    with pytest.raises(SecurityError):
        verify_issued_by(cert, old_ca, now=NOW)
    assert not list(pki.glob("*.tmp"))


def test_a_private_key_readable_by_others_is_refused(pki: Path) -> None:
    ca_paths(pki).key.chmod(0o640)
    with pytest.raises(SecurityError, match="accessible to group or others"):
        ensure_identity(pki, Identity.client(SWARM, "new"), now=NOW)


# --- expiry ---------------------------------------------------------------------------


def test_check_validity_tells_the_time_left_and_refuses_outside_the_validity(pki: Path) -> None:
    cert = load_certificate(identity_paths(pki, Identity.client(SWARM, "cli")).cert)
    assert check_validity(cert, now=NOW + dt.timedelta(days=300)) == dt.timedelta(days=65)
    with pytest.raises(CertificateExpiredError, match="valid only from 2029-12-31T23:55:00"):
        check_validity(cert, now=NOW + dt.timedelta(days=365))
    with pytest.raises(CertificateExpiredError):
        check_validity(cert, now=NOW - dt.timedelta(hours=1))  # not yet valid
    # Within the renewal margin counts as expired.
    with pytest.raises(CertificateExpiredError):
        check_validity(cert, now=NOW + dt.timedelta(days=340), margin=dt.timedelta(days=30))


def test_an_expired_certificate_is_reported_and_renewed_only_on_request(pki: Path) -> None:
    later = NOW + dt.timedelta(days=400)
    with pytest.raises(CertificateExpiredError, match=r"router\.lab\.pem: valid only from"):
        init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki), now=later)
    done = init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki, replace=True), now=later)
    by_status = {d.common_name: d.status for d in done}
    assert by_status["swarmrec CA lab"] == "kept"  # the CA is valid for ten years
    assert by_status["r0.detector.lab"] == "replaced"
    cert = load_certificate(identity_paths(pki, Identity.service(SWARM, "detector", 0)).cert)
    assert check_validity(cert, now=later) == dt.timedelta(days=365)


def test_renew_days_reissues_certificates_about_to_expire(pki: Path) -> None:
    soon = NOW + dt.timedelta(days=350)
    with pytest.raises(CertificateExpiredError):
        init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki, renew_days=30), now=soon)
    init_pki(PkiSettings(swarm=SWARM, robots=2, out=pki), now=soon)  # without the margin: still fine


# --- settings and the command ------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"robots": 0}, "robots must be"),
        ({"swarm": "a/b"}, "swarm name"),
        ({"kinds": ()}, "kinds must be"),
        ({"kinds": ("verifier", "verifier")}, "kinds must be"),
        ({"kinds": ("router",)}, "service kind"),
        ({"clients": ("cli", "cli")}, "must not repeat"),
        ({"clients": ("Cli",)}, "client name"),
        ({"key_type": "rsa"}, "key type"),
        ({"cert_days": 400, "ca_days": 365}, "cert_days <= ca_days"),
        ({"renew_days": 365}, "renew_days"),
        ({"router_names": ()}, "at least one name"),
        ({"router_names": ("bad name",)}, "neither an IP address nor a DNS name"),
    ],
)
def test_settings_are_validated_on_construction(
    kwargs: dict[str, object], message: str, tmp_path: Path
) -> None:
    args: dict[str, object] = {"swarm": SWARM, "robots": 2, "out": tmp_path}
    args.update(kwargs)
    with pytest.raises(ConfigError, match=message):
        PkiSettings(**args)  # type: ignore[arg-type]  # deliberately wrong values


def test_main_reports_what_it_created_and_then_that_it_kept_everything(tmp_path: Path) -> None:
    settings = PkiSettings(swarm=SWARM, robots=1, out=tmp_path / "pki")
    out = io.StringIO()
    assert main(settings, stdout=out) == 0
    n = 1 + 1 + len(SERVICE_KINDS) + 3  # CA, router, services, client, operator, gateway
    assert f"{n} created, 0 replaced, 0 kept" in out.getvalue()
    assert out.getvalue().count("created  ") == n
    out = io.StringIO()
    assert main(settings, stdout=out) == 0
    assert f"0 created, 0 replaced, {n} kept" in out.getvalue()


def test_main_stops_on_a_conflict_and_says_nothing_was_overwritten(pki: Path) -> None:
    identity_paths(pki, Identity.router(SWARM)).cert.unlink()
    before = snapshot(pki)
    out = io.StringIO()
    assert main(PkiSettings(swarm=SWARM, robots=2, out=pki), stdout=out, now=NOW) == 1
    assert "router.lab.key: exists without router.lab.pem" in out.getvalue()
    assert "nothing was overwritten" in out.getvalue()
    assert snapshot(pki) == before


def test_the_security_package_exports_what_its_all_lists() -> None:
    for name in security.__all__:
        assert hasattr(security, name), name
