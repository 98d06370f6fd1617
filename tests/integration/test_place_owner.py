"""The place-owner service over a real router: bad input, idempotent stores, restarts,
and start-up refusals.

A 2-robot swarm (a verifier and a place-owner per robot, real processes, the shipped
k = 10 centres with 5 clusters per robot) is seeded through the owners' own ``process``
endpoints with frames whose descriptors are seeded random unit vectors. Each bad request
then must come back as an ErrorReply with its code, be counted in
``swarmrec_rejected_requests_total{endpoint,code}`` of the service that refused it, and
leave everything stored as it was: the owners' and verifiers' record logs byte for byte,
the faiss snapshots, the stored counts, and the answers to re-sent stored queries (a
stored frame sent again with the same descriptor is answered by a fresh search and not
stored twice, so it probes an owner without changing it).

Which cluster a descriptor belongs to is computed here from the centres file with numpy
(nearest centre, squared L2), and which robot owns it from the paper's seeded assignment.

The swarm runs in the explicit insecure mode: the cases send requests as whoever they
need to be, which the router's access control would refuse first (tested in
test_swarm_mtls.py).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from swarmrec.client import ZenohClient
from swarmrec.deployments.base import SwarmStartError
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import read_metrics
from swarmrec.errors import NoReply
from swarmrec.models import DESCRIPTOR_CENTRES, LANDMARK_MODEL, shipped_model
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.settings import DetectorSettings, PlaceSettings, VprSettings
from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.render import write_rgbd_sequence
from swarmrec.vpr.clusters import random_assignment
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm
from tests.integration.support import (
    Answer,
    answering,
    endpoint_key,
    metric,
    metrics_url,
    protobuf,
    raw_request,
    reply_of,
    request,
    write_office,
)

N_ROBOTS, C, D = 2, 5, 128
K = N_ROBOTS * C
SEEDED = 12  # frames per robot
FLOAT32, INT8 = 1, 2
TABLE = random_assignment(N_ROBOTS, C, seed=0)


def unit(seed: int) -> np.ndarray:
    v = np.random.default_rng([seed, 77]).normal(size=D).astype(np.float32)
    return v / np.linalg.norm(v)


def nearest_cluster(x: np.ndarray) -> int:
    """The nearest shipped centre of ``x`` (squared L2), straight from the file."""
    with np.load(shipped_model(DESCRIPTOR_CENTRES)) as data:
        centres = np.asarray(data[f"k{K}"], np.float64)
    return int(np.argmin(((centres - x.astype(np.float64)) ** 2).sum(axis=1)))


def int8_code(x: np.ndarray) -> bytes:
    """The wire's int8 layout, written out here: float32 scale, then round(x / scale) as int8."""
    scale = np.float32(np.abs(x).max() / np.float32(127))
    q = np.clip(np.rint(x / scale), -127, 127).astype(np.int8)
    return struct.pack("<f", float(scale)) + q.tobytes()


def frame_msg(robot: int, t: int, x: np.ndarray) -> pb.PlaceFrame:
    """Robot ``robot``'s frame ``t``: float32 descriptor ``x`` and three objects."""
    c = pb.Constellation(labels=[0, 41, 56], positions_mm=[100 * t, 20, 1500, -300, 10, 2000, 250, -40, 1800])
    return pb.PlaceFrame(
        robot_id=robot,
        frame_index=t,
        frame_id=f"f{t}",
        descriptor=x.astype("<f4").tobytes(),
        encoding=FLOAT32,
        constellation=c,
    )


@dataclass
class Seeded:
    """One stored frame: its robot, frame, descriptor and the cluster (and owner) it went to."""

    robot: int
    frame: int
    x: np.ndarray
    cluster: int

    @property
    def owner(self) -> int:
        return TABLE.owners[self.cluster]

    def query(self, **changes: Any) -> pb.PlaceQuery:
        fields: dict[str, Any] = {
            "robot_id": self.robot,
            "frame_index": self.frame,
            "descriptor": int8_code(self.x),
            "encoding": INT8,
            "cluster": self.cluster,
        }
        fields.update(changes)
        return pb.PlaceQuery(**{k: v for k, v in fields.items() if v is not None})


@dataclass
class Swarm:
    local: LocalDeployment
    client: ZenohClient
    seeded: list[Seeded]

    @property
    def session(self) -> zenoh.Session:
        return self.client.session

    def key(self, kind: str, robot: int, endpoint: str) -> str:
        return endpoint_key(self.local, kind, robot, endpoint)

    def url(self, kind: str, robot: int) -> str:
        return metrics_url(self.local.find(kind, robot))


def seed(local: LocalDeployment, client: ZenohClient) -> list[Seeded]:
    seeded = []
    for t in range(SEEDED):
        for r in range(N_ROBOTS):
            x = unit(100 * r + t)
            report = reply_of(
                answering(
                    client.session, endpoint_key(local, "place-owner", r, "process"), frame_msg(r, t, x)
                ),
                pb.PlaceReport,
            )
            assert report.answered and report.cluster == nearest_cluster(x)
            assert report.owner_robot_id == TABLE.owners[report.cluster]
            seeded.append(Seeded(r, t, x, report.cluster))
    # Both owners hold frames and some queries crossed robots (the cases below rely on it).
    assert {s.owner for s in seeded} == {0, 1} and any(s.owner != s.robot for s in seeded)
    return seeded


@pytest.fixture(scope="module")
def swarm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Swarm]:
    tmp = tmp_path_factory.mktemp("place-owner")
    vpr = VprSettings(vpr_clusters_per_robot=C, vpr_snapshot_every=4)
    with (
        running_swarm(
            tmp,
            "place-owner",
            PlaceSettings(),
            vpr,
            robots=N_ROBOTS,
            kinds=("verifier", "place-owner"),
            security="insecure",
            swarm_kinds=(),
            max_message_bytes=4096,
        ) as local,
        local.client(5.0) as client,
    ):
        yield Swarm(local, client, seed(local, client))


def probes(s: Swarm) -> dict[str, bytes]:
    """Every seeded frame sent again to its owner: answered by a fresh search, stored once."""
    out = {}
    for item in s.seeded:
        answer = request(s.session, s.key("place-owner", item.owner, "query"), item.query())
        out[f"{item.robot}/{item.frame}"] = reply_of(answer, pb.PlaceMatch).SerializeToString()
    return out


def stored_state(s: Swarm) -> dict[str, Any]:
    """What a bad request could have changed: logs and snapshots byte for byte, stored counts,
    the probes' answers."""
    out: dict[str, Any] = {}
    files = sorted(p for p in s.local.data_dir.rglob("*") if p.is_file() and p.suffix in (".log", ".npz"))
    names = {p.name for p in files}
    assert {"place-owner.log", "verifier.log", "owner-index.npz"} <= names, names
    for path in files:
        out[str(path.relative_to(s.local.data_dir))] = path.read_bytes()
    for r in range(N_ROBOTS):
        out[f"owner {r} stored"] = metric(s.url("place-owner", r), "swarmrec_place_owner_stored_descriptors")
        out[f"verifier {r} stored"] = metric(s.url("verifier", r), "swarmrec_verifier_stored_frames")
    out["probes"] = probes(s)
    assert out["owner 0 stored"] + out["owner 1 stored"] == N_ROBOTS * SEEDED
    return out


def rejected(url: str) -> dict[tuple[str, str], float]:
    return {
        (dict(labels)["endpoint"], dict(labels)["code"]): v
        for (name, labels), v in read_metrics(url).items()
        if name == "swarmrec_rejected_requests_total"
    }


def check_refused(s: Swarm, robot: int, endpoint: str, answer: Answer, code: str, text: str) -> None:
    assert answer.error is not None, f"expected {code}, got a reply"
    assert answer.code == code, answer.error.message
    assert text in answer.error.message, answer.error.message


def _x(s: Swarm, owner: int) -> Seeded:
    """A seeded frame whose cluster ``owner`` owns (and whose robot is not the owner, when one is)."""
    mine = [i for i in s.seeded if i.owner == owner]
    return next((i for i in mine if i.robot != owner), mine[0])


def _nan_float32(x: np.ndarray) -> bytes:
    y = x.copy()
    y[3] = np.nan
    return y.astype("<f4").tobytes()


def _inf_float32(x: np.ndarray) -> bytes:
    y = x.copy()
    y[0] = np.inf
    return y.astype("<f4").tobytes()


# Each case: (name, what to change in a valid query, code, text of the reason). The query goes to
# robot 0's owner, for a cluster it owns, from a frame of the other robot, at a new frame index.
NEW = 500
QUERY_CASES: list[tuple[str, dict[str, Any], str, str]] = [
    ("wrong length", {"descriptor": b"\x01" * 131}, "ERROR_CODE_INVALID_ARGUMENT", "are 132 bytes, got 131"),
    (
        "float32 as int8",
        {"encoding": INT8, "descriptor": b"\x00" * 512},
        "ERROR_CODE_INVALID_ARGUMENT",
        "are 132 bytes",
    ),
    ("unknown encoding", {"encoding": 9}, "ERROR_CODE_INVALID_ARGUMENT", "encoding 9 is not one of"),
    ("no encoding", {"encoding": 0}, "ERROR_CODE_INVALID_ARGUMENT", "encoding 0 is not one of"),
    ("NaN", {"encoding": FLOAT32, "descriptor": "nan"}, "ERROR_CODE_INVALID_ARGUMENT", "NaN or inf"),
    ("inf", {"encoding": FLOAT32, "descriptor": "inf"}, "ERROR_CODE_INVALID_ARGUMENT", "NaN or inf"),
    ("NaN scale", {"descriptor": "nan scale"}, "ERROR_CODE_INVALID_ARGUMENT", "non-finite scale"),
    (
        "zero vector",
        {"encoding": FLOAT32, "descriptor": bytes(512)},
        "ERROR_CODE_INVALID_ARGUMENT",
        "L2 norm 0",
    ),
    (
        "unknown cluster",
        {"cluster": K},
        "ERROR_CODE_INVALID_ARGUMENT",
        f"not one of the swarm's {K} clusters",
    ),
    ("cluster of another robot", {"cluster": "other"}, "ERROR_CODE_FAILED_PRECONDITION", "not robot 0's"),
    ("another table", {"assignment_version": 3}, "ERROR_CODE_FAILED_PRECONDITION", "assignment version 3"),
    ("no cluster", {"cluster": None}, "ERROR_CODE_INVALID_ARGUMENT", "has no cluster"),
    ("no robot", {"robot_id": None}, "ERROR_CODE_INVALID_ARGUMENT", "has no robot_id"),
    ("no frame", {"frame_index": None}, "ERROR_CODE_INVALID_ARGUMENT", "has no frame_index"),
    ("robot outside the swarm", {"robot_id": 2}, "ERROR_CODE_INVALID_ARGUMENT", "not in this swarm of 2"),
    ("frame index too high", {"frame_index": 1 << 20}, "ERROR_CODE_INVALID_ARGUMENT", "below 1048576"),
]


def _bad_query(s: Swarm, changes: dict[str, Any]) -> pb.PlaceQuery:
    base = _x(s, 0)
    fields = dict(changes)
    d = fields.get("descriptor")
    if d == "nan":
        fields["descriptor"] = _nan_float32(base.x)
    elif d == "inf":
        fields["descriptor"] = _inf_float32(base.x)
    elif d == "nan scale":
        fields["descriptor"] = struct.pack("<f", float("nan")) + int8_code(base.x)[4:]
    if fields.get("cluster") == "other":
        fields["cluster"] = _x(s, 1).cluster
    fields.setdefault("frame_index", NEW)
    return base.query(**fields)


@pytest.mark.parametrize(("name", "changes", "code", "text"), QUERY_CASES, ids=[c[0] for c in QUERY_CASES])
def test_an_owner_refuses_a_bad_query_counts_it_and_stores_nothing(
    swarm: Swarm, name: str, changes: dict[str, Any], code: str, text: str
) -> None:
    before = stored_state(swarm)
    counted = rejected(swarm.url("place-owner", 0))
    answer = request(swarm.session, swarm.key("place-owner", 0, "query"), _bad_query(swarm, changes))
    check_refused(swarm, 0, "query", answer, code, text)
    after_counts = rejected(swarm.url("place-owner", 0))
    assert after_counts.get(("query", code), 0) == counted.get(("query", code), 0) + 1
    assert sum(after_counts.values()) == sum(counted.values()) + 1
    assert stored_state(swarm) == before


def test_malformed_bytes_are_refused_as_malformed(swarm: Swarm) -> None:
    before = stored_state(swarm)
    # Field 1 as a 64-bit fixed value: a wire type PlaceQuery's robot_id (a varint) never has.
    answer = raw_request(
        swarm.session,
        swarm.key("place-owner", 1, "query"),
        b"\x09" + bytes(8),
        protobuf("swarmrec.v1.PlaceQuery"),
        caller=1,  # a robot's (a request that names none is refused before it is read)
    )
    assert answer.code in ("ERROR_CODE_MALFORMED",), answer.error
    assert rejected(swarm.url("place-owner", 1)).get(("query", "ERROR_CODE_MALFORMED"), 0) >= 1
    assert stored_state(swarm) == before


def test_a_stored_frame_sent_again_is_answered_once_stored_and_other_content_is_already_exists(
    swarm: Swarm,
) -> None:
    item = _x(swarm, 0)
    before = stored_state(swarm)
    again = reply_of(
        request(swarm.session, swarm.key("place-owner", 0, "query"), item.query()), pb.PlaceMatch
    )
    assert again.SerializeToString() == before["probes"][f"{item.robot}/{item.frame}"]
    other = unit(9999)
    answer = request(
        swarm.session, swarm.key("place-owner", 0, "query"), item.query(descriptor=int8_code(other))
    )
    check_refused(swarm, 0, "query", answer, "ERROR_CODE_ALREADY_EXISTS", "already stored here")
    assert stored_state(swarm) == before


def test_a_frame_of_another_robot_than_the_sender_is_refused_and_stores_nothing(swarm: Swarm) -> None:
    # The sender is the robot the key names (keys.CALLER_BOUND): robot 1 with robot 0's frame.
    item = _x(swarm, 0)
    before = stored_state(swarm)
    answer = request(swarm.session, swarm.key("place-owner", 0, "query"), item.query(), caller=item.robot + 1)
    check_refused(swarm, 0, "query", answer, "ERROR_CODE_PERMISSION_DENIED", "its own frames only")
    assert stored_state(swarm) == before


PROCESS_CASES: list[tuple[str, dict[str, Any], str, str]] = [
    ("another robot's frame", {"robot_id": 1}, "ERROR_CODE_INVALID_ARGUMENT", "only its own robot's"),
    ("NaN descriptor", {"descriptor": "nan"}, "ERROR_CODE_INVALID_ARGUMENT", "NaN or inf"),
    (
        "short descriptor",
        {"descriptor": b"\x00" * 100},
        "ERROR_CODE_INVALID_ARGUMENT",
        "are 512 bytes, got 100",
    ),
    ("no constellation", {"constellation": None}, "ERROR_CODE_INVALID_ARGUMENT", "has no constellation"),
    ("label past the list", {"labels": [0, 80, 3]}, "ERROR_CODE_UNKNOWN_LABEL", "outside the label list"),
    (
        "stored frame, other objects",
        {"frame_index": 0, "labels": [1, 2, 3]},
        "ERROR_CODE_ALREADY_EXISTS",
        "frame 0",
    ),
]


@pytest.mark.parametrize(
    ("name", "changes", "code", "text"), PROCESS_CASES, ids=[c[0] for c in PROCESS_CASES]
)
def test_a_querier_refuses_a_bad_frame_counts_it_and_stores_nothing(
    swarm: Swarm, name: str, changes: dict[str, Any], code: str, text: str
) -> None:
    before = stored_state(swarm)
    counted = rejected(swarm.url("place-owner", 0))
    x = unit(4242)
    msg = frame_msg(0, changes.get("frame_index", NEW + 1), x)
    if "robot_id" in changes:
        msg.robot_id = changes["robot_id"]
    if changes.get("descriptor") == "nan":
        msg.descriptor = _nan_float32(x)
    elif "descriptor" in changes:
        msg.descriptor = changes["descriptor"]
    if "constellation" in changes:
        msg.ClearField("constellation")
    if "labels" in changes:
        msg.constellation.labels[:] = changes["labels"]
    answer = request(swarm.session, swarm.key("place-owner", 0, "process"), msg)
    check_refused(swarm, 0, "process", answer, code, text)
    assert (
        rejected(swarm.url("place-owner", 0)).get(("process", code), 0)
        == counted.get(("process", code), 0) + 1
    )
    assert stored_state(swarm) == before


def test_the_assignment_is_served_to_clients_as_the_versioned_table_the_swarm_routes_by(swarm: Swarm) -> None:
    for r in range(N_ROBOTS):
        reply = reply_of(
            request(swarm.session, swarm.key("place-owner", r, "assignment"), pb.AssignmentRequest()),
            pb.AssignmentReply,
        )
        table = json.loads(reply.table_json)
        assert table["format"] == "swarmrec.vpr.assignment/1" and table["version"] == reply.version == 0
        assert tuple(table["owners"]) == TABLE.owners
        assert list(reply.owned_clusters) == list(TABLE.clusters_of(r))
        assert reply.dimension == D and reply.wire_encoding == INT8
        assert len(reply.centres_sha256) == 64


# --- restarts ---------------------------------------------------------------------------


def _restored_counts(log: Path) -> dict[str, int]:
    """The last "owner index restored" line of a place-owner's log."""
    lines = [json.loads(x) for x in log.read_text().splitlines() if '"owner index restored"' in x]
    assert lines, f"{log} has no restore line"
    return {k: int(lines[-1][k]) for k in ("from_snapshot", "from_log", "skipped")}


@pytest.mark.parametrize("how", ["sigterm", "sigkill"])
def test_a_restarted_owner_answers_exactly_as_before(tmp_path: Path, how: str) -> None:
    vpr = VprSettings(vpr_clusters_per_robot=C, vpr_snapshot_every=4)
    with (
        running_swarm(
            tmp_path,
            f"restart-{how}",
            PlaceSettings(),
            vpr,
            robots=N_ROBOTS,
            kinds=("verifier", "place-owner"),
            security="insecure",
            swarm_kinds=(),
        ) as local,
        local.client(5.0) as client,
    ):
        s = Swarm(local, client, seed(local, client))
        before = stored_state(s)
        owner = 0
        held = int(before[f"owner {owner} stored"])
        assert held > 4  # more than one snapshot's worth, so the log holds some beyond it
        sp = local.find("place-owner", owner)
        if how == "sigterm":
            assert local.stop_process(sp) == 0  # the service saves its index as it stops
        else:
            sp.proc.kill()  # no chance to save: the log holds what the last snapshot does not
            sp.proc.wait()
            sp.release()
        (restarted,) = local.start_robot(owner, ["place-owner"])
        local.wait_started([restarted])
        counts = _restored_counts(restarted.log_path)
        if how == "sigterm":
            assert counts == {"from_snapshot": held, "from_log": 0, "skipped": 0}
        else:
            assert counts["from_snapshot"] == held - held % 4 and counts["from_log"] == held % 4
        answering(client.session, s.key("place-owner", owner, "assignment"), pb.AssignmentRequest())
        after = stored_state(s)
    # The snapshot file is rewritten at a clean stop (same entries, maybe another byte layout).
    for key in [k for k in before if k.endswith("owner-index.npz")]:
        before.pop(key)
        after.pop(key)
    assert after == before


# --- start-up refusals -------------------------------------------------------------------


def test_a_detector_given_a_model_that_is_not_a_descriptor_model_does_not_start(tmp_path: Path) -> None:
    folder = tmp_path / "rgbd"
    write_rgbd_sequence(generate_office(OfficeConfig(n_frames=4)), folder)
    wrong = str(shipped_model(LANDMARK_MODEL))  # a 19-way image classifier: an image in, the wrong vector out
    parts = (
        PlaceSettings(),
        DetectorSettings(detector_mode="rgbd", dataset=str(folder)),
        VprSettings(place_method="dvpr", descriptor_model=wrong, vpr_clusters_per_robot=C),
    )
    with (
        running_swarm(
            tmp_path,
            "wrong-model",
            *parts,
            robots=N_ROBOTS,
            kinds=("detector",),
            start=False,
            security="insecure",
            swarm_kinds=(),
        ) as local,
        pytest.raises(SwarmStartError, match=r"landmark_cnn.onnx: expected a float32 output \[N, 128\]"),
    ):
        local.wait_started(local.start_robot(0), timeout_s=60)


def test_a_replaying_detector_cannot_run_the_full_image_method(tmp_path: Path) -> None:
    dataset = write_office(tmp_path / "dataset", n_frames=20)
    parts = (PlaceSettings(), DetectorSettings(dataset=str(dataset)), VprSettings(place_method="dvpr"))
    with (
        running_swarm(
            tmp_path,
            "replay-dvpr",
            *parts,
            robots=N_ROBOTS,
            kinds=("detector",),
            start=False,
            security="insecure",
            swarm_kinds=(),
        ) as local,
        pytest.raises(
            SwarmStartError, match="place_method dvpr describes camera images: run the detector in rgbd"
        ),
    ):
        local.wait_started(local.start_robot(0), timeout_s=60)


def test_an_owner_whose_centres_lack_k_does_not_start(tmp_path: Path) -> None:
    vpr = VprSettings(vpr_clusters_per_robot=3)  # k = 6: the shipped file has 10, 20, 40, 80, 160
    with (
        running_swarm(
            tmp_path,
            "no-k",
            PlaceSettings(),
            vpr,
            robots=N_ROBOTS,
            kinds=("place-owner",),
            start=False,
            security="insecure",
            swarm_kinds=(),
        ) as local,
        pytest.raises(SwarmStartError, match=r"no centres for k=6 \(it has k in \[10, 20, 40, 80, 160\]\)"),
    ):
        local.wait_started(local.start_robot(0), timeout_s=60)


# --- the access control (mutual TLS, the deployment's default) ------------------------------


def test_the_router_lets_each_identity_call_only_what_the_full_image_method_needs(tmp_path: Path) -> None:
    """A client reads the table and the loop closures but cannot store into an owner; a robot's
    detector drives only its own place-owner; a place-owner queries any robot's owner. Each
    denial is measured behind an allowed request sent after it."""
    vpr = VprSettings(vpr_clusters_per_robot=C)
    with running_swarm(
        tmp_path,
        "po-acl",
        PlaceSettings(),
        vpr,
        robots=N_ROBOTS,
        kinds=("verifier", "place-owner"),
        swarm_kinds=(),
    ) as local:
        assert local.pki_dir is not None and local.endpoint.startswith("tls/")
        s = local.spec_swarm

        def session_of(cn: str) -> ZenohClient:
            assert local.pki_dir is not None
            return ZenohClient([local.endpoint], s, timeout_s=3.0, tls=TlsFiles.in_dir(local.pki_dir, cn))

        def stored() -> dict[int, int]:
            with local.client(role="client") as c:
                return {m.robot: m.stored_items for m in c.members() if m.kind == "place-owner"}

        x = unit(31)
        cluster = nearest_cluster(x)
        owner = TABLE.owners[cluster]
        query = pb.PlaceQuery(
            robot_id=1 - owner, frame_index=0, descriptor=int8_code(x), encoding=INT8, cluster=cluster
        )
        key = endpoint_key(local, "place-owner", owner, "query")
        with session_of(f"client.cli.{s}") as client:
            caller = Caller(client.session, None, 3.0)
            with pytest.raises(NoReply):  # a client may not store into an owner
                caller.call(key, query, pb.PlaceMatch, target_robot=owner)
            table = caller.call(
                endpoint_key(local, "place-owner", owner, "assignment"),
                pb.AssignmentRequest(),
                pb.AssignmentReply,
                target_robot=owner,
            )
            assert tuple(json.loads(table.table_json)["owners"]) == TABLE.owners
            caller.call(
                endpoint_key(local, "place-owner", owner, "loop_closures"),
                pb.LoopClosuresRequest(),
                pb.LoopClosureList,
                target_robot=owner,
            )
        assert stored() == {0: 0, 1: 0}
        with session_of(f"r1.detector.{s}") as detector:
            caller = Caller(detector.session, 1, 3.0)
            with pytest.raises(NoReply):  # robot 1's detector drives robot 1's place-owner only
                caller.call(
                    endpoint_key(local, "place-owner", 0, "process"),
                    frame_msg(0, 0, x),
                    pb.PlaceReport,
                    target_robot=0,
                )
            report = caller.call(
                endpoint_key(local, "place-owner", 1, "process"),
                frame_msg(1, 0, x),
                pb.PlaceReport,
                target_robot=1,
            )
            assert report.answered and report.owner_robot_id == owner
        assert sum(stored().values()) == 1
        with session_of(f"r{1 - owner}.place-owner.{s}") as querier:
            caller = Caller(querier.session, 1 - owner, 3.0)
            second = pb.PlaceQuery(
                robot_id=1 - owner,
                frame_index=7,
                descriptor=int8_code(unit(32)),
                encoding=INT8,
                cluster=nearest_cluster(unit(32)),
            )
            target = TABLE.owners[second.cluster]
            caller.call(
                endpoint_key(local, "place-owner", target, "query"),
                second,
                pb.PlaceMatch,
                target_robot=target,
            )
        assert sum(stored().values()) == 2
