"""The one life of a run's swarm (`deployments.base.running`), on a recording stand-in of a
deployment: what it calls and in which order, the timings and exit codes it keeps, a swarm
that holds an earlier run's data refused, and the swarm stopped whatever happens. The
pipelines that use it run on real deployments in the integration tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, cast

import pytest

from swarmrec.deployments.base import Deployment, SwarmSpec, running
from swarmrec.errors import ConfigError


@dataclass
class Member:
    kind: str
    robot: int
    stored_items: int


@dataclass
class Recording:
    """Says what was asked of it; its members hold ``stored`` items each."""

    stored: int = 0
    calls: list[str] = field(default_factory=list)
    description: str = "recording"

    def start(self, spec: Any, *, progress: bool = False) -> None:
        self.calls.append("start")

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        self.calls.append("wait_ready")

    @contextmanager
    def client(self, timeout_s: float = 5.0, *, role: str = "operator") -> Iterator[Any]:
        self.calls.append(f"client:{role}")

        class Client:
            def members(_self) -> list[Member]:
                return [Member("verifier", 0, self.stored), Member("router", 0, 0)]

        yield Client()

    def stop(self) -> dict[str, int]:
        self.calls.append("stop")
        return {"router": 0, "verifier-0": -15}


SPEC = cast(SwarmSpec, object())


def test_it_starts_waits_then_stops_and_keeps_the_timings_and_exit_codes() -> None:
    d = Recording()
    timings = {"prepare_s": 1.0}
    with running(cast(Deployment, d), SPEC, timings=timings) as session:
        assert d.calls == ["start", "wait_ready"]
        assert session.timings is timings and timings["start_s"] >= 0
        d.calls.append("work")
    assert d.calls == ["start", "wait_ready", "work", "stop"]
    assert session.exit_codes == {"router": 0, "verifier-0": -15}
    assert set(timings) == {"prepare_s", "start_s", "stop_s"}


def test_a_swarm_holding_an_earlier_runs_data_is_refused_and_stopped() -> None:
    d = Recording(stored=3)
    refused = pytest.raises(ConfigError, match=r"earlier run \(\{'verifier-0': 3\}\); start it afresh")
    with refused, running(cast(Deployment, d), SPEC, held_data="start it afresh"):
        d.calls.append("work")
    # Read with the read-only identity; the work never ran; the swarm was stopped.
    assert d.calls == ["start", "wait_ready", "client:client", "stop"]
    # A workload whose services keep nothing across runs does not ask.
    d = Recording(stored=3)
    with running(cast(Deployment, d), SPEC):
        pass
    assert d.calls == ["start", "wait_ready", "stop"]


def test_the_swarm_is_stopped_when_the_work_fails() -> None:
    d = Recording()
    with pytest.raises(RuntimeError, match="replay broke"), running(cast(Deployment, d), SPEC):
        raise RuntimeError("replay broke")
    assert d.calls[-1] == "stop"
