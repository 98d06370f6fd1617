"""The router service: a zenoh router (a Python session in router mode runs the
same routing runtime as zenohd; ../shared/ZENOH.md).

It listens on ``--listen`` endpoints and routes every other service's traffic;
it holds no state, so restarting it loses nothing (clients reconnect on their
own). This is the reference; the default (``data_plane`` compiled) is the compiled
router, ``dataplane/src/router.rs``, which also counts every refused handshake and
every message the access control denied (:class:`~swarmrec.services.metrics.RouterMetrics`).
This one exports those families but cannot count: the Python binding's zenoh is
built without its statistics and gives no hook into its TLS listener
(docs/security.md, "What the router counts"). It runs on the same runner as every
service (its registry entry sets router mode): metrics (``swarmrec_service_ready`` for health checks), the
``info`` endpoint, a liveliness token, signals.
"""

from __future__ import annotations

from swarmrec.runtime import ServiceBase, ServiceContext

__all__ = ["Router"]


class Router(ServiceBase):
    """No endpoints of its own: the session does the routing."""

    def __init__(self, ctx: ServiceContext) -> None:
        ctx.log.info(
            "routing (refusals not counted: the compiled router counts them)",
            extra={"fields": {"listen": list(ctx.bus.listen)}},
        )
