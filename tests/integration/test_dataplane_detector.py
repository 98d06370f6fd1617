"""The compiled detector (replay mode, ``data_plane = compiled``) against the reference.

Real processes over a real router, two robots, each service a process of its own, the
same recorded frames and the same sequence of requests for each implementation:

* steps while robot 0's descriptor is not running yet (its frames wait in the outbox,
  ``queued``), then with it (the waiting frames go first and come back as
  ``late_reports``), a frame that cannot go on the wire (a coordinate past the int32
  millimetre range: refused INVALID_ARGUMENT), a frame the descriptor refuses for what it
  is (too many objects: TOO_LARGE), steps while the descriptor is stopped again, steps
  past the end (``finished``), and bad requests (no step, a negative rate, a classify);
* then robot 0's detector is stopped with frames still waiting, and the *other*
  implementation is started on its data folder: it finds them in the outbox and delivers
  them. Every answer is the same, byte for byte (the reports' timing aside), in both
  orders, and so is what the detectors say of themselves (``pending_items``).
"""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import pytest

from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.settings import DetectorSettings, IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm
from tests.integration.support import endpoint_key
from tests.integration.support import request as ask

FRAMES = 32  # 16 a robot
UNSENDABLE, TOO_MANY = 5, 9  # robot 0's frames
MAX_OBJECTS = 12


def write_frames(folder: Path, seed: int) -> Path:
    """Two robots' frames of a dozen places (robot 1 revisits robot 0's), one frame with a
    coordinate no int32 millimetre holds and one with more objects than a frame may have."""
    rng = random.Random(seed)
    places = [
        [(rng.randrange(80), [rng.uniform(-4.0, 4.0) for _ in range(3)]) for _ in range(rng.randint(5, 8))]
        for _ in range(6)
    ]
    folder.mkdir(parents=True)
    for i in range(FRAMES):
        objs = [(label, [v + rng.gauss(0.0, 0.02) for v in p]) for label, p in places[i % 6]]
        if i == UNSENDABLE:
            objs[0] = (objs[0][0], [3.0e6, 0.0, 1.0])
        if i == TOO_MANY:
            objs = [
                (rng.randrange(80), [rng.uniform(-4, 4) for _ in range(3)]) for _ in range(MAX_OBJECTS + 2)
            ]
        text = "".join(f"{COCO_NAMES[label]} {x!r} {y!r} {z!r}\n" for label, (x, y, z) in objs)
        (folder / f"{1000 + i}.000000.txt").write_text(text, encoding="utf-8")
    return folder


def timeless(reply: pb.StepReply) -> bytes:
    if reply.HasField("report"):
        reply.report.duration_us = 0
    for r in reply.late_reports:
        r.duration_us = 0
    return reply.SerializeToString()


class Session:
    """One swarm's requests, and what each got."""

    def __init__(self, d: LocalDeployment) -> None:
        self.d = d
        self.answers: list[tuple[str, bytes | None, str, str]] = []

    def call(self, label: str, kind: str, robot: int, endpoint: str, msg: object) -> None:
        with self.d.client(20.0) as client:
            a = ask(client.session, endpoint_key(self.d, kind, robot, endpoint), msg, timeout_s=20.0)  # type: ignore[arg-type]
        ok = timeless(pb.StepReply.FromString(a.ok)) if a.ok is not None and endpoint == "step" else a.ok
        self.answers.append((label, ok, a.code, a.error.message if a.error is not None else ""))

    def step(self, robot: int, t: int) -> None:
        self.call(f"step {robot}/{t}", "detector", robot, "step", pb.StepRequest(step=t))

    def pending(self, robot: int, when: str) -> None:
        with self.d.client(5.0) as client:
            replies = list(client.session.get(endpoint_key(self.d, "detector", robot, "info"), timeout=5.0))
        info = pb.MemberInfo.FromString(replies[0].ok.payload.to_bytes())
        self.answers.append((f"pending {robot} {when}", None, str(info.pending_items), str(info.n_labels)))


def start(d: LocalDeployment, robot: int, kinds: list[str], plane: str | None = None) -> None:
    if plane is not None:
        d.spec = dataclasses.replace(d.spec, bus=d.spec.bus.with_(data_plane=plane))
    d.wait_started(d.start_robot(robot, kinds), 60.0)


def play(
    tmp: Path, name: str, first: str, then: str, dataset: Path
) -> list[tuple[str, bytes | None, str, str]]:
    with running_swarm(
        tmp,
        name,
        PlaceSettings(lockstep=True, max_objects_per_frame=MAX_OBJECTS),
        IndexSettings(retry_interval_s=0.2),
        # The retrier never fires on its own here: what is delivered when is the steps' doing.
        DetectorSettings(dataset=str(dataset), outbox_retry_s=3600.0),
        robots=2,
        kinds=["index-shard", "verifier", "descriptor", "detector"],
        swarm_kinds=(),
        security="insecure",
        start=False,
        data_plane=first,
    ) as d:
        start(d, 1, ["index-shard", "verifier", "descriptor", "detector"])
        start(d, 0, ["index-shard", "verifier", "detector"])
        assert d.find("detector", 0).info.get("dispatch") == (
            "compiled" if first == "compiled" else "channel"
        )
        with d.client(10.0) as client:
            client.wait_index_settled(30.0)
        s = Session(d)
        for t in range(3):  # robot 0's descriptor is not there: its frames wait
            s.step(0, t)
            s.step(1, t)
        s.pending(0, "with no descriptor")
        start(d, 0, ["descriptor"])
        for t in range(3, 12):
            s.step(0, t)
            s.step(1, t)
        d.stop_process(d.find("descriptor", 0))
        for t in range(12, 14):
            s.step(0, t)
            s.step(1, t)
        s.pending(0, "with the descriptor stopped")
        s.call("no step", "detector", 0, "step", pb.StepRequest())
        s.call("negative rate", "detector", 0, "replay", pb.ReplayRequest(rate_hz=-0.1))
        s.call("classify", "detector", 0, "classify", pb.ClassifyRequest(round_id=1))
        # The other implementation on the same data folder: it finds frames 12 and 13 waiting.
        d.stop_process(d.find("detector", 0))
        start(d, 0, ["detector"], plane=then)
        assert d.find("detector", 0).info.get("dispatch") == ("compiled" if then == "compiled" else "channel")
        s.pending(0, "restarted")
        start(d, 0, ["descriptor"])
        for t in range(14, 17):  # 16 is past the end: finished
            s.step(0, t)
            s.step(1, t)
        s.pending(0, "at the end")
        return s.answers


@pytest.mark.parametrize(("first", "then"), [("python", "compiled"), ("compiled", "python")])
def test_the_compiled_detector_plays_frames_as_the_python_reference(
    tmp_path: Path, request: pytest.FixtureRequest, first: str, then: str
) -> None:
    dataset = write_frames(tmp_path / "frames", 20261128)
    # Each order against the reference alone: the Python detector throughout.
    name = f"det-{first[0]}{then[0]}"
    reference = play(tmp_path / "reference", name, "python", "python", dataset)
    got = play(tmp_path / "run", name, first, then, dataset)
    assert len(got) == len(reference)
    for r, g in zip(reference, got, strict=True):
        assert r == g, (r, g)
    # About something: queued frames, late reports, both refusals, a finished step, reports with matches.
    by_label = {label: (ok, code, message) for label, ok, code, message in reference}
    pending = [
        by_label[f"pending 0 {when}"][1]
        for when in ("with no descriptor", "with the descriptor stopped", "restarted", "at the end")
    ]
    assert pending == ["3", "2", "2", "0"]
    first_step = pb.StepReply.FromString(by_label["step 0/0"][0] or b"")
    assert first_step.queued and first_step.pending == 1
    delivered = pb.StepReply.FromString(by_label["step 0/3"][0] or b"")
    assert [r.frame_index for r in delivered.late_reports] == [0, 1, 2] and delivered.HasField("report")
    assert by_label[f"step 0/{UNSENDABLE}"][1:] == (
        "ERROR_CODE_INVALID_ARGUMENT",
        f"descriptor refused frame {UNSENDABLE}: frame {UNSENDABLE}: object 0 at [3000000.0, 0.0, 1.0] m "
        "is out of the int32 millimetre range",
    )
    assert by_label[f"step 0/{TOO_MANY}"][1] == "ERROR_CODE_TOO_LARGE"
    assert by_label["no step"][1] == "ERROR_CODE_INVALID_ARGUMENT"
    assert by_label["negative rate"][1:] == (
        "ERROR_CODE_INVALID_ARGUMENT",
        "rate_hz must be >= 0, got -0.10000000149011612",
    )
    assert by_label["classify"][1] == "ERROR_CODE_FAILED_PRECONDITION"
    restarted = pb.StepReply.FromString(by_label["step 0/14"][0] or b"")
    assert [r.frame_index for r in restarted.late_reports] == [12, 13] and restarted.HasField("report")
    finished = pb.StepReply.FromString(by_label["step 0/16"][0] or b"")
    assert finished.finished and finished.pending == 0
    reports = [
        pb.StepReply.FromString(ok) for label, ok, code, _ in reference if label.startswith("step") and ok
    ]
    assert sum(len(r.report.matches) for r in reports) > 0
