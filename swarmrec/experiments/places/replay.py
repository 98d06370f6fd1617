"""Driving a swarm's detectors through a dataset, and collecting what they found.

* :func:`replay_lockstep`: step t of every robot finishes before step t + 1
  starts, exactly as the offline decentralized evaluation simulates;
* :func:`replay_free`: every detector replays its whole block at a rate (or as
  fast as the swarm answers); the reports are collected from the query events.

A robot that does not answer a step, or whose report never comes, is recorded
as a missing (robot, step) slot rather than stopping the run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
from tqdm import tqdm

from swarmrec.client import ZenohClient
from swarmrec.errors import SwarmrecError
from swarmrec.experiments.places.settings import PlacesSettings
from swarmrec.runtime import keys
from swarmrec.wire import messages as pb

__all__ = ["Replay", "collect_loop_closures", "replay", "replay_free", "replay_lockstep"]


@dataclass
class Replay:
    """What a replay got back: the query reports, the slots with no answer, errors, timings."""

    reports: list[pb.QueryReport]
    missing: list[tuple[int, int]]  # (robot, step) slots with no answer
    errors: list[str]
    step_seconds: list[float]
    wall_s: float


def replay_lockstep(
    client: ZenohClient,
    blocks: list[range],
    settings: PlacesSettings,
    on_step: Callable[[int], None] | None,
    before_step: Callable[[int], None] | None = None,
) -> Replay:
    per = max((len(b) for b in blocks), default=0)
    reports: list[pb.QueryReport] = []
    missing: list[tuple[int, int]] = []
    errors: list[str] = []
    step_s: list[float] = []
    t0 = time.perf_counter()
    step_timeout = 6 * settings.request_timeout_s
    desc = f"swarm x{settings.robots} lock-step"
    with tqdm(total=per, desc=desc, unit="step", disable=not settings.progress, leave=False) as bar:
        for t in range(per):
            if before_step is not None:
                before_step(t)
            ts = time.perf_counter()
            answered: set[int] = set()
            for item in client.step(t, step_timeout):
                if isinstance(item, Exception):
                    errors.append(f"step {t}: {item}")
                    continue
                answered.add(item.robot_id)
                if not item.finished:
                    reports.append(item.report)
            missing += [(r, t) for r, b in enumerate(blocks) if t < len(b) and r not in answered]
            step_s.append(time.perf_counter() - ts)
            bar.update(1)
            if on_step is not None:
                on_step(t)
    return Replay(reports, missing, errors, step_s, time.perf_counter() - t0)


def replay_free(client: ZenohClient, blocks: list[range], settings: PlacesSettings) -> Replay:
    rate = 0.0 if settings.pace == "fast" else float(settings.pace)
    expected = sum(len(b) for b in blocks)
    reports: list[pb.QueryReport] = []
    errors: list[str] = []
    key = keys.event(settings.swarm, "query", "*")
    t0 = time.perf_counter()
    desc = f"swarm x{settings.robots} at {settings.pace}"
    with (
        client.session.declare_subscriber(key) as sub,
        tqdm(total=expected, desc=desc, unit="frame", disable=not settings.progress, leave=False) as bar,
    ):
        for item in client.replay(rate):
            if isinstance(item, Exception):
                errors.append(f"replay: {item}")
        idle_limit = 6 * settings.request_timeout_s
        last = time.perf_counter()
        while len(reports) < expected:
            sample = sub.try_recv()
            if sample is None:
                if time.perf_counter() - last > idle_limit:
                    errors.append(f"no report for {idle_limit:g} s; {expected - len(reports)} frames missing")
                    break
                time.sleep(0.002)
                continue
            assert isinstance(sample, zenoh.Sample)
            reports.append(pb.QueryReport.FromString(sample.payload.to_bytes()))
            last = time.perf_counter()
            bar.update(1)
    seen = {(r.robot_id, r.frame_index) for r in reports}
    missing = [(r, t) for r, b in enumerate(blocks) for t in range(len(b)) if (r, t) not in seen]
    return Replay(reports, missing, errors, [], time.perf_counter() - t0)


def replay(
    client: ZenohClient,
    blocks: list[range],
    settings: PlacesSettings,
    on_step: Callable[[int], None] | None,
    before_step: Callable[[int], None] | None = None,
) -> Replay:
    """The replay ``settings.pace`` asks for (``before_step``: lock-step only)."""
    if settings.lockstep:
        return replay_lockstep(client, blocks, settings, on_step, before_step)
    return replay_free(client, blocks, settings)


def collect_loop_closures(client: ZenohClient, robots: int, result: Replay) -> list[pb.LoopClosure]:
    """Every robot's loop closures after a replay; a robot that does not answer adds an
    error to ``result`` rather than losing the others'."""
    closures: list[pb.LoopClosure] = []
    for r in range(robots):
        try:
            closures += client.loop_closures(r)
        except SwarmrecError as e:
            result.errors.append(f"loop closures of robot {r}: {e}")
    return closures
