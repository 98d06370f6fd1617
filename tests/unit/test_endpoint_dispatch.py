"""Which way requests reach an endpoint's workers (``dispatch``): zenoh's channels for a
process of a few services, queues for one hosting many (tests/integration/test_hosting.py
and test_endpoint_queue.py run both)."""

from __future__ import annotations

import pytest

from swarmrec.errors import ConfigError
from swarmrec.runtime.runner import dispatch_by_queue
from swarmrec.runtime.settings import AUTO_QUEUE_ABOVE, BusSettings, load_config


def test_auto_feeds_workers_from_queues_only_in_a_process_of_many_services() -> None:
    assert not dispatch_by_queue("auto", 1)
    assert not dispatch_by_queue("auto", 20)  # five robots of four services: the two were even
    assert AUTO_QUEUE_ABOVE == 32
    assert not dispatch_by_queue("auto", 32)
    assert dispatch_by_queue("auto", 33)
    assert dispatch_by_queue("auto", 52)  # thirteen robots: queues were faster


def test_an_explicit_choice_holds_whatever_the_process_hosts() -> None:
    assert dispatch_by_queue("queue", 1)
    assert not dispatch_by_queue("channel", 400)


def test_dispatch_is_a_setting_of_every_service_and_refuses_other_values() -> None:
    assert BusSettings().dispatch == "auto"
    config = load_config((BusSettings,), env={"SWARMREC_DISPATCH": "queue"})
    assert config.get(BusSettings).dispatch == "queue"
    with pytest.raises(ConfigError, match="dispatch"):
        load_config((BusSettings,), env={"SWARMREC_DISPATCH": "fifo"})
