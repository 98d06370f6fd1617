"""Mutual TLS and default-deny access control for the swarm's zenoh links.

    identity   who is who: the certificate common-name scheme
    certs      X.509 in memory: the CA, end certificates, their checks
    pki        the PKI on disk: create what is missing, never overwrite silently
    acl        the router's access-control section, generated from the swarm's shape

The TLS settings of a zenoh config (router and client side, or the loud insecure
mode) are part of the bus plumbing: :mod:`swarmrec.runtime.tls`. This package sits
above the services (identities name the registry's kinds) and beside the deployments,
which create the PKI and hand each process its identity.

docs/security.md has the threat model and what each identity may do.
"""

from swarmrec.security.acl import access_control, configure_access_control, grants
from swarmrec.security.identity import SERVICE_KINDS, Identity, parse_common_name
from swarmrec.security.pki import PkiSettings, ensure_ca, ensure_identity, init_pki

__all__ = [
    "SERVICE_KINDS",
    "Identity",
    "PkiSettings",
    "access_control",
    "configure_access_control",
    "ensure_ca",
    "ensure_identity",
    "grants",
    "init_pki",
    "parse_common_name",
]
