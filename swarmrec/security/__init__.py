"""Mutual TLS and default-deny access control for the swarm's zenoh links.

    identity   who is who: the certificate common-name scheme
    certs      X.509 in memory: the CA, end certificates, their checks
    pki        the PKI on disk: create what is missing, never overwrite silently
    zenoh_tls  TLS settings of a zenoh config, router and client side, or the loud insecure mode
    acl        the router's access-control section, generated from the swarm's shape

docs/security.md has the threat model and what each identity may do.

The service runner should import ``swarmrec.security.zenoh_tls`` (the
module, not this package): it depends on nothing of swarmrec but its errors,
whereas ``identity`` and ``acl`` import ``swarmrec.services.keys``, whose
package imports the runner.
"""

from swarmrec.security.acl import access_control, configure_access_control, grants
from swarmrec.security.identity import SERVICE_KINDS, Identity, parse_common_name
from swarmrec.security.pki import PkiSettings, ensure_ca, ensure_identity, init_pki
from swarmrec.security.zenoh_tls import (
    TlsFiles,
    configure_client_tls,
    configure_insecure,
    configure_router_tls,
    require_tls_endpoints,
    tls_endpoint,
)

__all__ = [
    "SERVICE_KINDS",
    "Identity",
    "PkiSettings",
    "TlsFiles",
    "access_control",
    "configure_access_control",
    "configure_client_tls",
    "configure_insecure",
    "configure_router_tls",
    "ensure_ca",
    "ensure_identity",
    "grants",
    "init_pki",
    "parse_common_name",
    "require_tls_endpoints",
    "tls_endpoint",
]
