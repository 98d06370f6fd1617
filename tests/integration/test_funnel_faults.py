"""A verifier that stops answering shows in the loop-closure funnel, candidate by candidate.

Three robots replay 300 synthetic frames in lock-step. After step 20 robot 2's
verifier is frozen (SIGSTOP) for four steps, then thawed (SIGCONT); after step 60
robot 1's verifier is killed (SIGKILL). Robot 2's candidates in the other robots'
queries of the frozen steps must end at the verification stage, never scored, as
``verifier_timeout`` or, once the router has given up on the frozen process (its
lease expired, or its queue to the process filled: CI saw this at the first frozen
step), as ``verifier_unreachable``; a caller cannot tell such a process from a dead
one, and the funnel reports what the caller saw. The frozen window ends when robot 2's
verifier answers again, not at SIGCONT: a process the router gave up on reconnects and
declares its endpoints again first, and compiled services replay the steps after the
thaw faster than that takes. Robot 1's candidates after the
kill must be ``verifier_unreachable``; no
candidate anywhere else fails verification, and the funnel still adds up. Robot 2's
own frames of the frozen steps wait in its detector's outbox (its descriptor cannot
store them in its own verifier) and are queried once the verifier is back.
"""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import time
from pathlib import Path

import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from tests.integration.support import endpoint_key

ROBOTS, FRAMES = 3, 300
FROZEN, THAWED, KILLED = 20, 24, 60  # after these steps
STOPPED, DEAD = 2, 1  # whose verifier
# Right after the kill the router may not have noticed yet: a query can still time out.
SETTLED = KILLED + 3


def _wait_answering(d: LocalDeployment, kind: str, robot: int, timeout_s: float = 30.0) -> None:
    """Until the service answers its ``info`` endpoint (fails the test after ``timeout_s``)."""
    key = endpoint_key(d, kind, robot, "info")
    deadline = time.monotonic() + timeout_s
    with d.client(1.0) as client:
        while not any(r.ok is not None for r in client.session.get(key, timeout=1.0)):
            assert time.monotonic() < deadline, f"{kind} {robot} did not answer again in {timeout_s:g} s"
            time.sleep(0.05)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_candidates_of_a_frozen_verifier_time_out_and_of_a_dead_one_are_unreachable(tmp_path: Path) -> None:
    out = tmp_path / "run"
    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=out,
        swarm="funnel-faults",
        request_timeout_s=2.0,
        progress=False,
        plots=False,
    )
    held: list[LocalDeployment] = []

    def hook(swarm: Deployment) -> None:
        assert isinstance(swarm, LocalDeployment)
        held.append(swarm)

    frozen: list[int] = []  # the pid of the verifier while it is stopped

    def on_step(t: int) -> None:
        if t == FROZEN:
            frozen.append(held[0].find("verifier", STOPPED).proc.pid)
            os.kill(frozen[0], signal.SIGSTOP)
        elif t == THAWED:
            os.kill(frozen.pop(), signal.SIGCONT)
            _wait_answering(held[0], "verifier", STOPPED)
        elif t == KILLED:
            proc = held[0].find("verifier", DEAD).proc
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)

    try:
        summary = main(settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step)
    finally:
        for pid in frozen:  # a failure between the two steps must not leave it stopped
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)

    rows = _rows(out / "funnel.csv")
    queries = {(int(q["robot"]), int(q["frame"])): q for q in _rows(out / "funnel_queries.csv")}
    frozen_failures = unreachable = 0
    for r in rows:
        qr, step, cand = int(r["query_robot"]), int(r["query_frame"]), int(r["candidate_robot"])
        q = queries[(qr, step)]
        verified = cand in {int(v) for v in q["verified_robots"].split()}
        failed = {int(v) for v in q["failed_verifiers"].split()}
        if FROZEN < step <= THAWED and cand == STOPPED and qr != STOPPED and verified:
            assert r["reason"] in ("verifier_timeout", "verifier_unreachable"), r
            assert r["stage"] == "verification", r
            assert STOPPED in failed
            assert r["score"] == ""  # never scored
            frozen_failures += 1
        elif step > SETTLED and cand == DEAD and verified:
            assert r["reason"] == "verifier_unreachable" and r["stage"] == "verification", r
            assert DEAD in failed
            unreachable += 1
        elif step <= FROZEN or THAWED < step <= KILLED or (step > SETTLED and cand != DEAD):
            assert not r["reason"].startswith("verifier_"), r
    assert frozen_failures > 0 and unreachable > 0
    assert summary.queries.late_frames > 0  # robot 2's frames of the frozen steps, delivered later
    # The dead verifier's robot missed every step after the kill (its frames wait in its
    # detector's outbox for good); the frozen robot's frames came late; the others none.
    missing = summary.queries.missing_by_robot
    assert (
        set(missing) <= {str(STOPPED), str(DEAD)}
        and missing.get(str(DEAD), 0) >= FRAMES // ROBOTS - KILLED - 2
    )
    funnel = summary.funnel
    assert funnel is not None
    assert funnel.inconsistent_queries == 0 and funnel.accepted_equals_loop_closures
    assert (
        funnel.by_reason.get("verifier_timeout", 0) + funnel.by_reason["verifier_unreachable"]
        >= frozen_failures + unreachable
    )
    assert funnel.by_reason["verifier_unreachable"] >= unreachable
    # The descriptors counted the same (a robot's counters are read before its services stop).
    scraped = funnel.scraped_by_reason
    assert scraped["verifier_timeout"] == funnel.by_reason.get("verifier_timeout", 0)
    assert scraped["verifier_unreachable"] == funnel.by_reason["verifier_unreachable"]
