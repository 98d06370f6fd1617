"""The landmark simulation over real processes: a zenoh router, and per robot a
detector in classifier mode and a fusion service, as ``swarmrec landmarks`` runs them.

Checked against things the swarm does not compute itself: each robot's own decision
equals the committed CNN run here, in this process, on the same rendered views (so the
PNG on the wire, the decode and the resize lose nothing); every robot's posterior
equals the core's Eq. 12 recomputed from the same vectors in the order it recorded;
every robot receives exactly the ``n * deg`` copies Algorithm 1 sends it; the
ClassifierOutput messages counted by Prometheus are exactly that number per round.
A second test sends a detector bad views and bad rounds: each gets a clear error
reply, is counted, and the robot goes on classifying.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from swarmrec.deployments.base import SwarmStartError
from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.landmarks.report import recognition_rates, write_landmark_report
from swarmrec.experiments.landmarks.simulation import (
    VIEW_PRESETS,
    LandmarkSettings,
    parse_law,
    render_views,
    run_simulation,
)
from swarmrec.fusion import generate_configuration
from swarmrec.fusion.classifier import LandmarkClassifier
from swarmrec.runtime import keys
from swarmrec.services.settings import ClassifierSettings, DetectorSettings
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import metric, metrics_url, reply_of, request

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROBOTS = 6
CONFIGURATIONS = 4
LAWS = ("paper:0", "agreement")


def test_a_small_street_simulation_fuses_over_zenoh_exactly_as_the_core_does(
    request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    settings = LandmarkSettings(
        out=tmp_path / "run",
        configurations=CONFIGURATIONS,
        robots=ROBOTS,
        laws=tuple(parse_law(law) for law in LAWS),
        swarm=swarm_name(request),
        progress=False,
    )
    result = run_simulation(settings, LocalDeployment.for_run(settings.out))
    assert result.errors == [] and result.failures == {}
    rounds = result.rounds
    assert len(rounds) == CONFIGURATIONS * len(LAWS) * ROBOTS

    # Every copy arrived, every robot heard every other, no message was refused.
    for r in rounds:
        assert r.complete and r.incorporated == ROBOTS - 1, r
        assert r.incorporated + r.duplicates == r.expected_deliveries
        assert r.rejected == 0
        assert r.core_difference == 0.0  # bit for bit: the same float32 vectors, the same order

    # The robots' own decisions are the CNN's on the views rendered here.
    classifier = LandmarkClassifier()
    views = render_views(result.configurations, settings.seed, VIEW_PRESETS[settings.views])
    by_key = {(r.configuration, r.law, r.robot): r for r in rounds}
    for config, images in zip(result.configurations, views, strict=True):
        probabilities = classifier.classify(images)
        for law in LAWS:
            for i in range(ROBOTS):
                record = by_key[(config.index, law, i)]
                assert record.decisions[0] == int(np.argmax(probabilities[i]))
                np.testing.assert_allclose(record.probabilities, probabilities[i], atol=1e-6)
                assert record.truth == int(config.landmarks[i])

    # Prometheus' count of flooded messages is Algorithm 1's: n copies per link direction per round.
    sent = result.metrics.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
    expected = sum(ROBOTS * int(c.adjacency.sum()) for c in result.configurations) * len(LAWS)
    assert sent["ClassifierOutput"] == expected

    # The report: figures, and rates that are the records' own.
    summary = write_landmark_report(result)
    for name in (
        "report.md",
        "results.json",
        "fig3_recognition.png",
        "fig4_configurations.png",
        "fig5_confusion.png",
    ):
        assert (settings.out / name).stat().st_size > 0
    saved = json.loads((settings.out / "results.json").read_text())
    assert saved == json.loads(json.dumps(summary.to_dict()))
    for law in LAWS:
        rate, count = recognition_rates(rounds, law, ROBOTS - 1)
        assert count.tolist() == [CONFIGURATIONS * ROBOTS] * ROBOTS
        assert saved["recognition"][law]["rate"] == [round(float(v), 4) for v in rate]
    assert saved["checks"]["core_max_difference"] == 0.0
    assert saved["bytes"]["classifier_output_messages_per_round"] == expected / (CONFIGURATIONS * len(LAWS))
    # The same views under two laws: the single robot's rate cannot differ.
    assert saved["recognition"]["paper:0"]["rate"][0] == saved["recognition"]["agreement"]["rate"][0]


@pytest.fixture
def classifier_swarm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LocalDeployment]:
    """Two robots, each a detector in classifier mode and a fusion service."""
    mode = DetectorSettings(detector_mode="classifier")
    name = swarm_name(request)
    with running_swarm(tmp_path, name, mode, kinds=["fusion", "detector"], request_timeout_s=5.0) as swarm:
        yield swarm


def png(image: np.ndarray, ext: str = ".png") -> bytes:
    ok, data = cv2.imencode(ext, np.ascontiguousarray(image[:, :, ::-1]))
    assert ok
    return bytes(data.tobytes())


def test_bad_views_and_bad_rounds_get_clear_errors_and_the_robot_goes_on(
    classifier_swarm: LocalDeployment,
) -> None:
    swarm = classifier_swarm.spec_swarm
    key = keys.endpoint(swarm, "detector", 0, "classify")
    url = metrics_url(classifier_swarm.find("detector", 0))
    view = render_views([generate_configuration(0, seed=0)], 0, VIEW_PRESETS["nominal"])[0][0]
    with classifier_swarm.client(5.0) as client:
        client.wait_for({(k, r) for r in range(2) for k in ("fusion", "detector")})
        s = client.session

        def classify(image: bytes, round_id: int, **extra: object) -> object:
            return request(
                s, key, pb.ClassifyRequest(round_id=round_id, image=image, neighbour_robot_ids=[1], **extra)
            )

        for bad, reason in [
            (b"", "empty"),
            (b"\x89PNG\r\n\x1a\n garbage", "decode"),
            (png(view)[:40], "decode"),
        ]:
            answer = classify(bad, 1)
            assert answer.code == "ERROR_CODE_INVALID_ARGUMENT" and reason in answer.error.message  # type: ignore[attr-defined]
        assert metric(url, "swarmrec_rejected_requests_total", endpoint="classify") == 3

        ok = reply_of(classify(png(view), 1), pb.ClassifyReply)
        assert ok.robot_id == 0 and ok.round_id == 1 and ok.fusion.sent == 1
        assert abs(sum(ok.probabilities) - 1.0) < 1e-5 and ok.decision == int(np.argmax(ok.probabilities))

        # The fusion service's refusals come back with its reason.
        again = classify(png(view), 1)
        assert again.code == "ERROR_CODE_INVALID_ARGUMENT" and "must advance" in again.error.message  # type: ignore[attr-defined]
        unknown = classify(png(view), 2, weight_law=pb.WeightLaw(name="magic"))
        assert unknown.code == "ERROR_CODE_INVALID_ARGUMENT" and "weight law" in unknown.error.message  # type: ignore[attr-defined]
        outside = request(s, key, pb.ClassifyRequest(round_id=3, image=png(view), neighbour_robot_ids=[7]))
        assert outside.code == "ERROR_CODE_INVALID_ARGUMENT" and "neighbours" in outside.error.message  # type: ignore[attr-defined]

        # A camera-sized JPEG is resized to the model's input; the same view decides the same.
        big = cv2.resize(view, (640, 480), interpolation=cv2.INTER_CUBIC)
        large = reply_of(classify(png(big, ".jpg"), 4), pb.ClassifyReply)
        assert large.round_id == 4 and abs(sum(large.probabilities) - 1.0) < 1e-5
        assert classifier_swarm.find("detector", 0).proc.poll() is None


def test_a_detector_with_a_model_that_is_not_onnx_stops_at_start_saying_why(
    request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    bad = tmp_path / "model.onnx"
    bad.write_bytes(b"not a model")
    parts = (DetectorSettings(detector_mode="classifier"), ClassifierSettings(classifier_model=str(bad)))
    with (
        pytest.raises(SwarmStartError, match="cannot load"),
        running_swarm(tmp_path, swarm_name(request), *parts, robots=1, kinds=["detector"], timeout_s=60.0),
    ):
        pass
