"""The router service: a zenoh router (a Python session in router mode runs the
same routing runtime as zenohd; ../shared/ZENOH.md).

It listens on ``--listen`` endpoints and routes every other service's traffic;
it holds no state, so restarting it loses nothing (clients reconnect on their
own). It runs on the same runner as every service (its registry entry sets
router mode): metrics (``swarmrec_service_ready`` for health checks), the
``info`` endpoint, a liveliness token, signals.
"""

from __future__ import annotations

from swarmrec.runtime import ServiceBase, ServiceContext

__all__ = ["Router"]


class Router(ServiceBase):
    """No endpoints of its own: the session does the routing."""

    def __init__(self, ctx: ServiceContext) -> None:
        ctx.log.info("routing", extra={"fields": {"listen": list(ctx.bus.listen)}})
