"""Detectors in rgbd mode with real processes over a real router: rendered RGB-D frames
go through an ONNX model to constellations, and on to place recognition; a corrupt PNG,
a missing depth image and an RGB/depth size mismatch are counted skips that the step
answers with an error, and the detector keeps serving; the main job runs from pixels
and reports the detector's figures; a model that does not load stops the detector at
start with a message naming it.

The model here is a tiny constant ONNX graph (tests/detector_models.py), so what the
detector finds is known; the project's trained model is compared with the renderer's
exact constellations in test_pixels_auc.py."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from swarmrec.datasets.tum_rgbd import read_tum_rgbd
from swarmrec.deployments.base import SwarmStartError
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings, main
from swarmrec.services.settings import DetectorSettings, PlaceSettings, RgbdSettings
from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.render import write_rgbd_sequence
from swarmrec.wire import messages as pb
from tests.detector_models import OFFICE_BOXES, constant_v8_model
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import endpoint_key, metric, metrics_url, reply_of, request

N_ROBOTS = 2
N_FRAMES = 80  # rendered: every 3rd frame of a 240-frame office path, 40 per robot
#: Global frame index -> how it is broken. Robot 0 plays frames 0-39, robot 1 frames 40-79.
#: The first 30 frames are all good (a run of them is checked against the offline evaluation).
BROKEN = {33: "corrupt_image", 36: "missing_image", 47: "size_mismatch"}


def _break(folder: Path) -> None:
    frames = read_tum_rgbd(folder).frames
    frames[33].rgb_path.write_bytes(frames[33].rgb_path.read_bytes()[:200])  # a PNG cut short
    frames[36].depth_path.unlink()
    cv2.imwrite(str(frames[47].depth_path), np.zeros((240, 320), np.uint16))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The office rendered as a TUM RGB-D folder, three of its frames broken, and the model."""
    tmp = tmp_path_factory.mktemp("rgbd")
    ds = generate_office(OfficeConfig(n_frames=3 * N_FRAMES))
    write_rgbd_sequence(ds, tmp / "rgbd", frames=range(0, 3 * N_FRAMES, 3))
    _break(tmp / "rgbd")
    constant_v8_model(tmp / "office.onnx", OFFICE_BOXES)
    return tmp


@pytest.fixture
def rgbd_swarm(rendered: Path, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[LocalDeployment]:
    parts = (
        PlaceSettings(lockstep=True),
        DetectorSettings(detector_mode="rgbd", dataset=str(rendered / "rgbd")),
        RgbdSettings(detector_model=str(rendered / "office.onnx")),
    )
    with running_swarm(tmp_path, swarm_name(request), *parts, robots=N_ROBOTS) as swarm:
        yield swarm


def test_rgbd_detectors_feed_place_recognition_and_skip_bad_frames(rgbd_swarm: LocalDeployment) -> None:
    per_robot = N_FRAMES // N_ROBOTS
    reports: dict[int, pb.QueryReport] = {}
    errors: dict[int, tuple[str, str]] = {}
    with rgbd_swarm.client(5.0) as client:
        for t in range(per_robot):
            for r in range(N_ROBOTS):
                key = endpoint_key(rgbd_swarm, "detector", r, "step")
                answer = request(client.session, key, pb.StepRequest(step=t), timeout_s=20.0)
                g = r * per_robot + t
                if answer.error is not None:
                    errors[g] = (answer.code, answer.error.message)
                else:
                    reports[g] = reply_of(answer, pb.StepReply).report

        # Every good frame reached place recognition; frames with objects queried and matched.
        assert sorted(errors) == sorted(BROKEN)
        assert len(reports) == N_FRAMES - len(BROKEN)
        queried = [rep for rep in reports.values() if rep.queried]
        assert len(queried) > N_FRAMES // 2
        assert sum(1 for rep in queried if rep.n_candidates) > len(queried) // 2
        assert sum(1 for rep in queried if rep.matches) >= 3
        # Each skip says which frame, why, and names the file.
        assert errors[33][0] == "ERROR_CODE_INVALID_ARGUMENT" and "skipped, corrupt_image" in errors[33][1]
        assert "frame 33 (" in errors[33][1] and "cannot decode RGB image" in errors[33][1]
        assert errors[36][0] == "ERROR_CODE_NOT_FOUND" and "skipped, missing_image" in errors[36][1]
        assert "depth image is missing" in errors[36][1] and ".png" in errors[36][1]
        assert errors[47][0] == "ERROR_CODE_INVALID_ARGUMENT" and "skipped, size_mismatch" in errors[47][1]
        assert "depth is 320x240 but its RGB image" in errors[47][1]

        # Counted by the detectors, by cause.
        url0, url1 = (metrics_url(rgbd_swarm.find("detector", r)) for r in range(N_ROBOTS))
        name = "swarmrec_detector_frames_total"
        assert metric(url0, name, outcome="corrupt_image") == 1
        assert metric(url0, name, outcome="missing_image") == 1
        assert metric(url1, name, outcome="size_mismatch") == 1
        made = metric(url0, name, outcome="detected") + metric(url0, name, outcome="no_objects")
        assert made == per_robot - 2
        assert metric(url0, "swarmrec_detector_objects_total") > 3 * made
        assert metric(url0, "swarmrec_rejected_requests_total", endpoint="step") == 2

        # The detector keeps serving: the bad frame is refused again, the others still answer.
        key0 = endpoint_key(rgbd_swarm, "detector", 0, "step")
        again = request(client.session, key0, pb.StepRequest(step=33), timeout_s=20.0)
        assert again.code == "ERROR_CODE_INVALID_ARGUMENT"
        finished = reply_of(request(client.session, key0, pb.StepRequest(step=per_robot)), pb.StepReply)
        assert finished.finished
        assert {(m.kind, m.robot) for m in client.members()} >= {("detector", 0), ("detector", 1)}
    assert all(sp.proc.poll() is None for sp in rgbd_swarm.procs)


def test_the_main_job_runs_from_an_rgbd_folder_and_reports_the_detector(
    rendered: Path, tmp_path: Path
) -> None:
    settings = PlacesSettings(
        pixels=PixelSettings(rgbd=rendered / "rgbd", model=str(rendered / "office.onnx")),
        robots=N_ROBOTS,
        out=tmp_path / "run",
        swarm="pixels-job",
        progress=False,
        plots=False,
    )
    summary = main(settings, LocalDeployment.for_run(settings.out))

    d = summary.detector
    assert d is not None and d.frames == N_FRAMES
    assert d.skipped == {outcome: 1 for outcome in BROKEN.values()}
    assert d.frames_without_constellation == len(BROKEN)
    assert d.frames_by_outcome["detected"] + d.frames_by_outcome.get("no_objects", 0) == 77
    assert 3 < d.objects_per_frame <= len(OFFICE_BOXES)
    assert set(d.stage_ms_mean) == {"decode", "detect", "points"}
    assert d.model == str((rendered / "office.onnx").resolve())
    assert d.camera["fx"] == pytest.approx(535.4)  # the render's own intrinsics, from boxes.json
    q = summary.queries
    assert q.frames_replayed == N_FRAMES - len(BROKEN)
    assert q.missing_slots == len(BROKEN) and len(q.errors) == len(BROKEN)
    assert summary.dataset.groundtruth and summary.auc is not None
    assert all(code == 0 for code in summary.exit_codes.values()), summary.exit_codes
    # What the detectors made, as a constellation dataset (skipped frames are empty files).
    assert len(list((tmp_path / "run" / "detections").glob("*.txt"))) == N_FRAMES


def test_the_main_job_checks_the_swarm_against_the_offline_evaluation_on_detected_constellations(
    rendered: Path, tmp_path: Path
) -> None:
    # The first 30 frames hold no broken one: no slot is missing, so the check runs, on the
    # constellations the detectors made (read back from their data folders).
    settings = PlacesSettings(
        source=DatasetSource(frames=30),
        pixels=PixelSettings(rgbd=rendered / "rgbd", model=str(rendered / "office.onnx")),
        robots=N_ROBOTS,
        out=tmp_path / "run",
        swarm="pixels-check",
        progress=False,
        plots=False,
    )
    summary = main(settings, LocalDeployment.for_run(settings.out))
    assert summary.dataset.frames == 30 and summary.detector is not None and summary.detector.skipped == {}
    assert summary.queries.missing_slots == 0
    assert summary.offline_check is not None and summary.offline_check.identical is True
    assert summary.offline_check.positive_pairs_swarm > 0  # the comparison is about something


def test_a_detector_whose_model_does_not_load_does_not_start_and_says_why(
    rendered: Path, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    (tmp_path / "broken.onnx").write_bytes(b"this is not an ONNX model")
    parts = (
        DetectorSettings(detector_mode="rgbd", dataset=str(rendered / "rgbd")),
        RgbdSettings(detector_model=str(tmp_path / "broken.onnx")),
    )
    with running_swarm(tmp_path, swarm_name(request), *parts, kinds=["detector"], start=False) as swarm:
        started = swarm.start_robot(0)
        with pytest.raises(SwarmStartError, match=r"broken\.onnx: onnxruntime cannot load it"):
            swarm.wait_started(started, timeout_s=60)
        assert started[0].proc.wait(timeout=10) == 2
