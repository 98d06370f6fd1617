"""The router service: a zenoh router (a Python session in router mode runs
the same routing runtime as zenohd; ../shared/ZENOH.md).

It listens on ``--listen`` endpoints and routes every other service's
traffic; it holds no state, so restarting it loses nothing (clients
reconnect on their own). Like every service it serves Prometheus metrics
(``swarmrec_service_ready`` for health checks) unless ``--metrics-port -1``.
"""

from __future__ import annotations

import json
import threading

import zenoh

from swarmrec.services.config import ServiceSettings
from swarmrec.services.metrics import ServiceMetrics
from swarmrec.services.runner import install_signals, service_logger, zenoh_config

__all__ = ["run_router"]


def run_router(settings: ServiceSettings, *, stop: threading.Event | None = None) -> int:
    """Route until SIGTERM/SIGINT (or ``stop``)."""
    stop = stop or threading.Event()
    install_signals(stop)
    log = service_logger("router", settings.robot, settings.log_level)
    settings = settings.with_(mode="router")
    metrics = ServiceMetrics.create("router", settings.robot, settings.swarm)
    with zenoh.open(zenoh_config(settings)):
        if settings.metrics_port >= 0:
            metrics.serve(settings.metrics_host, settings.metrics_port)
        metrics.ready.set(1)
        log.info("ready", extra={"fields": {"listen": list(settings.listen), "metrics_url": metrics.url}})
        print(
            json.dumps(
                {
                    "event": "ready",
                    "service": "router",
                    "listen": list(settings.listen),
                    "metrics_url": metrics.url,
                }
            ),
            flush=True,
        )
        stop.wait()
        metrics.ready.set(0)
        log.info("stopping")
    metrics.close()
    return 0
