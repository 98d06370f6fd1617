"""Driving a swarm's detectors through a dataset, and collecting what they found.

* :func:`replay_lockstep`: step t of every robot finishes before step t + 1
  starts, exactly as the offline decentralized evaluation simulates;
* :func:`replay_free`: every detector replays its whole block at a rate (or as
  fast as the swarm answers); the reports are collected from the query events.

A robot that does not answer a step, or whose report never comes, is recorded
as a missing (robot, step) slot rather than stopping the run. A frame a detector
could not hand to its descriptor at its step waits in the detector's outbox and
is delivered later (``late``); after the last step the job asks for steps past
the end, which flush the outboxes, until none has frames pending.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh
from tqdm import tqdm

from swarmrec.client import ZenohClient
from swarmrec.errors import TRANSIENT_CODES, RemoteError, SwarmrecError
from swarmrec.experiments.places.settings import ReplaySettings
from swarmrec.runtime import keys
from swarmrec.wire import messages as pb

__all__ = ["Replay", "collect_loop_closures", "replay", "replay_free", "replay_lockstep"]

#: How long a robot that does not answer a step is asked again before it counts as gone.
STEP_RETRY_S = 10.0
STEP_RETRY_POLL_S = 0.25
#: How long the job waits after the last step for the detectors' outboxes to empty.
FLUSH_TIMEOUT_S = 120.0
#: ... giving up sooner when no frame was delivered for this long.
FLUSH_STALL_S = 10.0
FLUSH_POLL_S = 0.2


@dataclass
class Replay:
    """What a replay got back: the query reports, the slots with no answer, errors, timings."""

    reports: list[pb.QueryReport]
    missing: list[tuple[int, int]]  # (robot, step) slots with no answer
    errors: list[str]
    step_seconds: list[float]
    wall_s: float
    #: (robot, step) slots whose frame was queued at its step and delivered later.
    late: list[tuple[int, int]] = field(default_factory=list)
    #: Frames still in the detectors' outboxes when the replay gave up waiting.
    pending: int = 0


def replay_lockstep(
    client: ZenohClient,
    blocks: list[range],
    settings: ReplaySettings,
    on_step: Callable[[int], None] | None,
    before_step: Callable[[int], None] | None = None,
) -> Replay:
    per = max((len(b) for b in blocks), default=0)
    reports: list[pb.QueryReport] = []
    queued: set[tuple[int, int]] = set()
    # Robots that did not answer a step in STEP_RETRY_S: asked once a step until they answer again.
    gone: set[int] = set()
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

            def take(item: pb.StepReply, t: int = t, answered: set[int] = answered) -> None:
                answered.add(item.robot_id)
                gone.discard(item.robot_id)
                reports.extend(item.late_reports)
                if item.HasField("report"):
                    reports.append(item.report)
                elif item.queued:
                    queued.add((item.robot_id, t))

            for item in client.step(t, step_timeout):
                if not isinstance(item, Exception):
                    take(item)
            due = [r for r, b in enumerate(blocks) if t < len(b) and r not in answered]
            errors += _retry_step(client, t, step_timeout, [r for r in due if r not in gone], take, gone)
            # A gone robot's later steps are its missing slots; its errors were said once.
            step_s.append(time.perf_counter() - ts)
            bar.update(1)
            if on_step is not None:
                on_step(t)
    pending = _flush_outboxes(client, per, step_timeout, reports, errors)
    delivered = {(r.robot_id, r.frame_index) for r in reports}
    slots = [(r, t) for r, b in enumerate(blocks) for t in range(len(b))]
    missing = [slot for slot in slots if slot not in delivered]
    late = sorted(slot for slot in queued if slot in delivered)
    return Replay(reports, missing, errors, step_s, time.perf_counter() - t0, late, pending)


def _retry_step(
    client: ZenohClient,
    t: int,
    step_timeout: float,
    robots: list[int],
    take: Callable[[pb.StepReply], None],
    gone: set[int],
) -> list[str]:
    """Ask ``robots`` for step ``t`` again, one by one, for up to STEP_RETRY_S (a router
    restarting, a detector busy flushing); a detector's step is idempotent. Robots that
    still do not answer join ``gone``; what each last said, as errors."""
    last: dict[int, str] = {}
    deadline = time.monotonic() + STEP_RETRY_S
    todo = list(robots)
    while todo and time.monotonic() < deadline:
        time.sleep(STEP_RETRY_POLL_S)
        for r in list(todo):
            for item in client.step(t, step_timeout, robot=r):
                if isinstance(item, Exception):
                    last[r] = str(item)
                    if isinstance(item, RemoteError) and item.code not in TRANSIENT_CODES:
                        todo.remove(r)  # the step itself is refused: asking again changes nothing
                    continue
                take(item)
                todo.remove(r)
                last.pop(r, None)
            if r in todo and r not in last:
                last[r] = "no answer"
    gone.update(todo)
    return [
        f"step {t}: robot {r}: {msg}"
        + (" (stopped answering; asked once a step from now on)" if r in todo else "")
        for r, msg in sorted(last.items())
    ]


def _flush_outboxes(
    client: ZenohClient, past_end: int, step_timeout: float, reports: list[pb.QueryReport], errors: list[str]
) -> int:
    """Ask for steps past the end until no detector has frames pending, or none was
    delivered for FLUSH_STALL_S (a robot whose verifier is gone), or FLUSH_TIMEOUT_S;
    the frames still pending."""
    pending = 0
    start = last_progress = time.monotonic()
    fewest: int | None = None
    while True:
        pending = 0
        answered = False
        for item in client.step(past_end, step_timeout):
            if isinstance(item, Exception):
                continue
            answered = True
            reports += item.late_reports
            pending += item.pending
        now = time.monotonic()
        if not pending or not answered:
            return pending
        if fewest is None or pending < fewest:
            fewest, last_progress = pending, now
        if now - last_progress > FLUSH_STALL_S or now - start > FLUSH_TIMEOUT_S:
            errors.append(
                f"{pending} frames still wait in the detectors' outboxes "
                f"(none delivered for {now - last_progress:.0f} s)"
            )
            return pending
        time.sleep(FLUSH_POLL_S)


def replay_free(client: ZenohClient, blocks: list[range], settings: ReplaySettings) -> Replay:
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
    settings: ReplaySettings,
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
