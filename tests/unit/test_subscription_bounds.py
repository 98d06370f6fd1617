"""A subscription's queue is bounded in bytes, and an oversized message never enters it.

The dispatcher's zenoh callback is called here with real zenoh samples' parts (ZBytes
payloads) and a real metrics registry; no worker runs, so whatever is accepted stays
queued, which is the case the bounds are for: messages arriving faster than handled."""

from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any, cast

import zenoh

from swarmrec.runtime.metrics import ServiceMetrics
from swarmrec.runtime.runner import SUBSCRIPTION_MAX_BYTES, Subscription, _SubscriptionDispatcher
from swarmrec.runtime.settings import BusSettings
from swarmrec.wire import messages as pb


def dispatcher(max_message_bytes: int = 1 << 20) -> tuple[_SubscriptionDispatcher, ServiceMetrics]:
    metrics = ServiceMetrics.create("fusion", 0, "bounds")
    ctx = SimpleNamespace(
        metrics=metrics,
        bus=BusSettings(swarm="bounds", max_message_bytes=max_message_bytes),
        log=logging.getLogger("test-bounds"),
    )
    sub = Subscription("inbox", pb.ClassifierOutput, lambda service, msg, rc: None)
    return _SubscriptionDispatcher(cast(Any, ctx), cast(Any, None), sub), metrics


def sample(size: int) -> Any:
    return SimpleNamespace(
        payload=zenoh.ZBytes(bytes(size)),
        encoding=zenoh.Encoding.APPLICATION_PROTOBUF,
        attachment=zenoh.ZBytes(b"1"),
        key_expr="swarmrec/bounds/fusion/0/inbox",
    )


def rejected(metrics: ServiceMetrics, code: str) -> float:
    value = metrics.registry.get_sample_value(
        "swarmrec_rejected_requests_total", {"endpoint": "inbox", "code": code}
    )
    return value or 0.0


def test_an_oversized_message_is_refused_before_it_is_queued() -> None:
    d, metrics = dispatcher(max_message_bytes=2000)

    for _ in range(50):
        d.on_sample(sample(2001))
    d.on_sample(sample(2000))

    assert d.inbox.qsize() == 1 and d.queued_bytes == 2000
    assert rejected(metrics, "ERROR_CODE_TOO_LARGE") == 50


def test_queued_bytes_are_bounded_and_freed_as_the_worker_takes_them() -> None:
    size = 1 << 20
    d, metrics = dispatcher(max_message_bytes=size)
    fits = SUBSCRIPTION_MAX_BYTES // size

    for _ in range(fits + 10):
        d.on_sample(sample(size))

    assert d.inbox.qsize() == fits and d.queued_bytes == fits * size
    assert rejected(metrics, "ERROR_CODE_UNAVAILABLE") == 10
    item = d.inbox.get_nowait()
    assert item is not None
    d.handle(item)  # (refused: zeros are no ClassifierOutput; its bytes are freed all the same)
    assert d.queued_bytes == (fits - 1) * size
    d.on_sample(sample(size))
    assert d.inbox.qsize() == fits
