"""Driving a full-image swarm's detectors through the frames, and what came back.

* :func:`replay_ordered` (``--pace lockstep``): one frame at a time, in the offline
  simulation's arrival order (step 0 of robots 0, 1, ..., then step 1, ...;
  :func:`swarmrec.vpr.simulation.arrival_order`). An owner's answer depends on which
  queries reached it before, so frames of one step are not sent at once: with them in
  flight together, robot 1's query could see robot 0's frame of the same step or not,
  by chance. In this order the swarm's answers are exactly the simulation's.
* :func:`replay_free` (a rate or ``fast``): every detector replays its block on its own;
  the reports are collected from ``events/place_query/<robot>``.

A robot that does not answer, or whose report never comes, is a missing (robot, step)
slot, not the end of the run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh
from tqdm import tqdm

from swarmrec.client import ZenohClient
from swarmrec.errors import SwarmrecError
from swarmrec.runtime import keys
from swarmrec.wire import messages as pb

__all__ = [
    "PlaceReplay",
    "TableChange",
    "collect_loop_closures",
    "rebalance",
    "replay_free",
    "replay_ordered",
]


@dataclass
class PlaceReplay:
    """The reports a replay got, by (robot, step), the slots without one, errors, timings."""

    reports: dict[tuple[int, int], pb.PlaceReport]
    missing: list[tuple[int, int]]
    errors: list[str]
    wall_s: float
    #: Seconds of each robot's step, as the operator saw it (lock-step only).
    step_seconds: list[float] = field(default_factory=list)


def replay_ordered(
    client: ZenohClient,
    blocks: list[range],
    timeout_s: float,
    *,
    progress: bool = False,
    after_step: Callable[[int, int], None] | None = None,
) -> PlaceReplay:
    """Lock-step replay; ``after_step(t, sent)`` runs after step ``t``, ``sent`` frames in
    (the live re-balancing asks the coordinator there, with no frame in flight)."""
    reports: dict[tuple[int, int], pb.PlaceReport] = {}
    missing: list[tuple[int, int]] = []
    errors: list[str] = []
    step_s: list[float] = []
    per = max((len(b) for b in blocks), default=0)
    total = sum(len(b) for b in blocks)
    caller = client.caller
    if caller is None:
        raise SwarmrecError("use the client in a with block")
    t0 = time.perf_counter()
    with tqdm(total=total, desc="dvpr lock-step", unit="frame", disable=not progress, leave=False) as bar:
        for t in range(per):
            for r, block in enumerate(blocks):
                if t >= len(block):
                    continue
                ts = time.perf_counter()
                key = keys.endpoint(client.swarm, "detector", r, "step")
                try:
                    reply = caller.call(
                        key, pb.StepRequest(step=t), pb.StepReply, target_robot=None, timeout_s=timeout_s
                    )
                except SwarmrecError as e:
                    errors.append(f"robot {r} step {t}: {e}")
                    missing.append((r, t))
                    continue
                finally:
                    step_s.append(time.perf_counter() - ts)
                    bar.update(1)
                if not reply.HasField("place"):
                    errors.append(
                        f"robot {r} step {t}: the detector sent no place report (not in dvpr mode?)"
                    )
                    missing.append((r, t))
                    continue
                reports[(r, t)] = reply.place
            if after_step is not None:
                after_step(t, sum(min(len(b), t + 1) for b in blocks))
    return PlaceReplay(reports, missing, errors, time.perf_counter() - t0, step_s)


@dataclass(frozen=True)
class TableChange:
    """One live re-balancing of a lock-step run: the table from arrival position ``at`` on."""

    at: int
    step: int
    reply: pb.RebalanceReply


def rebalance(client: ZenohClient, robots: int, timeout_s: float) -> pb.RebalanceReply:
    """Ask the coordinator, the lowest live place-owner, to re-balance now; the reply comes
    once every owner moved. Robots are tried from 0 up: one that is down does not answer,
    one above the coordinator refuses, the coordinator re-balances."""
    errors = []
    for robot in range(robots):
        key = keys.endpoint(client.swarm, "place-owner", robot, "rebalance")
        try:
            return client.call(
                key, pb.RebalanceRequest(), pb.RebalanceReply, target_robot=None, timeout_s=timeout_s
            )
        except SwarmrecError as e:
            errors.append(f"robot {robot}: {e}")
    raise SwarmrecError("no place-owner re-balanced: " + "; ".join(errors))


def replay_free(
    client: ZenohClient, blocks: list[range], rate_hz: float, idle_limit_s: float, *, progress: bool = False
) -> PlaceReplay:
    expected = sum(len(b) for b in blocks)
    reports: dict[tuple[int, int], pb.PlaceReport] = {}
    errors: list[str] = []
    key = keys.event(client.swarm, "place_query", "*")
    t0 = time.perf_counter()
    with (
        client.session.declare_subscriber(key) as sub,
        tqdm(total=expected, desc="dvpr replay", unit="frame", disable=not progress, leave=False) as bar,
    ):
        for item in client.replay(rate_hz):
            if isinstance(item, Exception):
                errors.append(f"replay: {item}")
        last = time.perf_counter()
        while len(reports) < expected:
            sample = sub.try_recv()
            if sample is None:
                if time.perf_counter() - last > idle_limit_s:
                    errors.append(
                        f"no report for {idle_limit_s:g} s; {expected - len(reports)} frames missing"
                    )
                    break
                time.sleep(0.002)
                continue
            assert isinstance(sample, zenoh.Sample)
            report = pb.PlaceReport.FromString(sample.payload.to_bytes())
            reports[(report.robot_id, report.frame_index)] = report
            last = time.perf_counter()
            bar.update(1)
    missing = [(r, t) for r, b in enumerate(blocks) for t in range(len(b)) if (r, t) not in reports]
    return PlaceReplay(reports, missing, errors, time.perf_counter() - t0)


def collect_loop_closures(client: ZenohClient, robots: int, result: PlaceReplay) -> list[pb.LoopClosure]:
    """Every place-owner's loop closures; one that does not answer adds an error to ``result``."""
    closures: list[pb.LoopClosure] = []
    for r in range(robots):
        key = keys.endpoint(client.swarm, "place-owner", r, "loop_closures")
        try:
            reply = client.call(key, pb.LoopClosuresRequest(), pb.LoopClosureList, target_robot=None)
        except SwarmrecError as e:
            result.errors.append(f"loop closures of robot {r}: {e}")
            continue
        closures += reply.loop_closures
    return closures
