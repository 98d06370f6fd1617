"""The router service: a zenoh router (a Python session in router mode runs
the same routing runtime as zenohd; ../shared/ZENOH.md).

It listens on ``--listen`` endpoints and routes every other service's
traffic; it holds no state, so restarting it loses nothing (clients
reconnect on their own).
"""

from __future__ import annotations

import json
import threading

import zenoh

from swarmrec.services.config import ServiceSettings
from swarmrec.services.runner import _install_signals, _logger, zenoh_config

__all__ = ["run_router"]


def run_router(settings: ServiceSettings, *, stop: threading.Event | None = None) -> int:
    """Route until SIGTERM/SIGINT (or ``stop``)."""
    stop = stop or threading.Event()
    _install_signals(stop)
    log = _logger("router", settings.robot, settings.log_level)
    settings = settings.with_(mode="router")
    with zenoh.open(zenoh_config(settings)):
        log.info("ready", extra={"fields": {"listen": list(settings.listen)}})
        print(
            json.dumps({"event": "ready", "service": "router", "listen": list(settings.listen)}), flush=True
        )
        stop.wait()
        log.info("stopping")
    return 0
