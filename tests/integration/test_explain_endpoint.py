"""A descriptor's ``explain`` endpoint, over a real router: what it holds, what aged out,
what it refuses, and ``swarmrec explain --connect`` against it.

Two robots whose descriptors keep only their last 2 reports (``explain_reports = 2``)
replay 4 lock-step steps of the synthetic office: each holds frames 2 and 3, frames 0
and 1 have aged out, frame 4 was never seen.
"""

from __future__ import annotations

import io
import random
from collections.abc import Iterator
from contextlib import redirect_stdout
from dataclasses import dataclass

import pytest

from swarmrec.cli import main as cli_main
from swarmrec.client import GatewayClient, ZenohClient
from swarmrec.deployments.local import LocalDeployment
from swarmrec.errors import RemoteError
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.settings import DetectorSettings, ExplainSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import schema_name
from tests.integration.conftest import running_swarm
from tests.integration.support import metric, metrics_url, protobuf, raw_request, request, write_office

ROBOTS, STEPS, KEPT = 2, 4, 2
HELD = pb.ReportStatus.REPORT_STATUS_HELD
AGED_OUT = pb.ReportStatus.REPORT_STATUS_AGED_OUT
NOT_SEEN = pb.ReportStatus.REPORT_STATUS_NOT_SEEN


@dataclass
class Swarm:
    local: LocalDeployment
    client: ZenohClient
    reports: dict[tuple[int, int], pb.QueryReport]

    def key(self, robot: int) -> str:
        return f"swarmrec/v1/{self.local.spec_swarm}/descriptor/{robot}/explain"


@pytest.fixture(scope="module")
def swarm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Swarm]:
    tmp = tmp_path_factory.mktemp("explain")
    dataset = write_office(tmp / "dataset", n_frames=100)
    parts = (
        PlaceSettings(lockstep=True),
        DetectorSettings(dataset=str(dataset)),
        ExplainSettings(explain_reports=KEPT),
    )
    with running_swarm(tmp, "explain-endpoint", *parts, robots=ROBOTS) as local, local.client(5.0) as client:
        reports: dict[tuple[int, int], pb.QueryReport] = {}
        for t in range(STEPS):
            for reply in client.step(t, timeout_s=10):
                assert isinstance(reply, pb.StepReply), reply
                reports[(reply.robot_id, t)] = reply.report
        yield Swarm(local, client, reports)


def test_the_last_reports_are_held_and_equal_what_the_step_answered(swarm: Swarm) -> None:
    for r in range(ROBOTS):
        for f in (STEPS - 2, STEPS - 1):
            reply = swarm.client.explain(r, f)
            assert reply.status == HELD and reply.robot_id == r
            assert reply.report == swarm.reports[(r, f)]
            assert (reply.reports_kept, reply.reports_held) == (KEPT, KEPT)
            assert (reply.oldest_frame_index, reply.newest_frame_index) == (STEPS - 2, STEPS - 1)
            # The rule its funnel applied: the paper preset and the default threshold.
            assert (reply.n_ret, reply.n_fq, reply.min_objects, reply.exclusion) == (4, 4, 3, 100)
            assert reply.loop_closure_min_score == pytest.approx(0.3)


def test_an_older_frame_has_aged_out_and_a_later_one_was_never_seen(swarm: Swarm) -> None:
    for f in range(STEPS - 2):
        aged = swarm.client.explain(1, f)
        assert aged.status == AGED_OUT and not aged.HasField("report")
    unseen = swarm.client.explain(1, STEPS)
    assert unseen.status == NOT_SEEN and not unseen.HasField("report")
    assert swarm.client.explain(1, MAX_FRAME_INDEX - 1).status == NOT_SEEN


def test_the_gateway_answers_explain_as_the_descriptor_does(swarm: Swarm) -> None:
    with swarm.local.gateway_client() as gateway:
        assert isinstance(gateway, GatewayClient)
        assert gateway.explain(0, STEPS - 1) == swarm.client.explain(0, STEPS - 1)
        # A robot without a descriptor: NOT_FOUND, the code the gateway maps the swarm's to.
        with pytest.raises(RemoteError) as info:
            gateway.explain(ROBOTS + 3, 0)
        assert info.value.code == pb.ErrorCode.ERROR_CODE_NOT_FOUND


EXPLAIN = schema_name(pb.ExplainRequest)
INVALID, MALFORMED = "ERROR_CODE_INVALID_ARGUMENT", "ERROR_CODE_MALFORMED"


@pytest.mark.parametrize(
    ("what", "payload", "schema", "code"),
    [
        ("no frame index", pb.ExplainRequest().SerializeToString(), EXPLAIN, INVALID),
        ("frame index 2**20", pb.ExplainRequest(frame_index=MAX_FRAME_INDEX).SerializeToString(), EXPLAIN,
         INVALID),
        ("random bytes", random.Random(3).randbytes(64), EXPLAIN, MALFORMED),
        ("a float where the frame index goes", pb.LoopClosuresRequest(min_score=0.5).SerializeToString(),
         None, MALFORMED),
        ("another message's schema", pb.StepRequest(step=1).SerializeToString(), schema_name(pb.StepRequest),
         INVALID),
    ],
)  # fmt: skip
def test_a_bad_explain_request_is_refused_counted_and_the_descriptor_still_answers(
    swarm: Swarm, what: str, payload: bytes, schema: str | None, code: str
) -> None:
    url = metrics_url(swarm.local.find("descriptor", 1))
    before = metric(url, "swarmrec_rejected_requests_total", endpoint="explain", code=code)
    answer = raw_request(swarm.client.session, swarm.key(1), payload, protobuf(schema) if schema else None)
    assert answer.code == code, what
    assert metric(url, "swarmrec_rejected_requests_total", endpoint="explain", code=code) == before + 1
    still = request(swarm.client.session, swarm.key(1), pb.ExplainRequest(frame_index=STEPS - 1))
    assert still.error is None and still.schema == schema_name(pb.ExplainReply)


def _cli(swarm: Swarm, *args: str) -> tuple[int, str]:
    assert swarm.local.pki_dir is not None
    connection = ["--connect", swarm.local.endpoint, "--swarm", swarm.local.spec_swarm]
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = cli_main(["explain", *args, *connection, "--pki-dir", str(swarm.local.pki_dir)])
    return code, buffer.getvalue()


def test_explain_connect_prints_every_candidate_of_a_held_frame(swarm: Swarm) -> None:
    report = swarm.reports[(1, STEPS - 1)]
    assert report.queried and report.candidates  # the table is about something
    code, text = _cli(swarm, "1", str(STEPS - 1))
    assert code == 0, text
    assert text.splitlines()[0].startswith(f"robot 1 frame {STEPS - 1}, live, robot 1's descriptor")
    rows = [line.split() for line in text.splitlines() if line.startswith("  ") and line.split()[0].isdigit()]
    assert [(int(r[0]), int(r[1])) for r in rows] == [(c.robot_id, c.frame_index) for c in report.candidates]


def test_explain_connect_says_when_a_frame_has_aged_out(swarm: Swarm) -> None:
    code, text = _cli(swarm, "0", "1")
    assert code == 3
    assert text.strip() == (
        "robot 0 frame 1 (live, robot 0's descriptor): frame 1 has aged out of robot 0's descriptor "
        f"memory: it holds the last 2 reports (frames {STEPS - 2} to {STEPS - 1}; explain_reports = 2)"
    )


def test_explain_connect_of_a_pair_says_a_live_swarm_keeps_no_shard_scores(swarm: Swarm) -> None:
    report = swarm.reports[(1, STEPS - 1)]
    listed = {(c.robot_id, c.frame_index) for c in report.candidates}
    other = next((0, f) for f in range(STEPS) if (0, f) not in listed)
    code, text = _cli(swarm, "1", str(STEPS - 1), "--with", *map(str, other))
    assert code == 0, text
    assert "shard / below_shard_cut: never a candidate" in text
    assert "A live swarm keeps no shard scores" in text
