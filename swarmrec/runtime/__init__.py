"""The bus plumbing every service shares: settings declared per component, key
expressions, request/response over zenoh, metrics, record logs, and the runner
that owns a service's lifecycle.

    from swarmrec.runtime import Endpoint, ServiceBase, ServiceContext, run_service

A service is a :class:`ServiceBase` with endpoints and subscriptions; the registry
(:mod:`swarmrec.services.registry`) names each kind's class, settings and metrics,
and :func:`run_service` runs it.
"""

from swarmrec.runtime.runner import (
    Endpoint,
    RequestContext,
    ServiceBase,
    ServiceContext,
    Subscription,
    run_service,
    zenoh_config,
)
from swarmrec.runtime.settings import BusSettings, Component, Config, StorageSettings, setting

__all__ = [
    "BusSettings",
    "Component",
    "Config",
    "Endpoint",
    "RequestContext",
    "ServiceBase",
    "ServiceContext",
    "StorageSettings",
    "Subscription",
    "run_service",
    "setting",
    "zenoh_config",
]
