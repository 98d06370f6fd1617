"""End to end from pixels: the synthetic office rendered as RGB-D frames, the project's
detector model in every robot's detector service, constellations, place recognition;
the same rendered sequence run again from the renderer's exact constellations (a perfect
detector with perfect depth). Both AUCs are printed and the pixel run must stay within
an honest margin of the exact one.

Ground truth follows the paper: a frame's scene point sits at its constellation's mean
depth, so each run has its own, and a detector that finds the near objects more often
than the far ones moves the scene points towards the camera and changes which pairs are
true closures. The two runs are therefore compared on the same truth, the exact run's
(the renderer's visible objects); the pixel run's AUC on its own truth is reported too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.tum import read_trajectory
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.groundtruth import ground_truth
from swarmrec.evaluation.pr import precision_recall
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings, main
from swarmrec.experiments.places.pipeline import as_on_the_wire

FRAMES = 600  # two loops around the desks; the paper preset ignores pairs <= 100 frames apart
ROBOTS = 4
#: How much AUC the run from pixels may lose against the exact constellations, on the same truth.
MARGIN = 0.10


@pytest.mark.slow
def test_the_swarm_from_pixels_recognises_places_nearly_as_well_as_from_exact_constellations(
    tmp_path: Path,
) -> None:
    common = {"robots": ROBOTS, "progress": False, "plots": False}
    pixels = main(
        PlacesSettings(
            source=DatasetSource(frames=FRAMES),
            pixels=PixelSettings(from_pixels=True),
            out=tmp_path / "pixels",
            swarm="auc-pixels",
            **common,  # type: ignore[arg-type]
        ),
        LocalDeployment.for_run(tmp_path / "pixels"),
    )
    rendered = tmp_path / "pixels" / "rgbd"
    exact = main(
        PlacesSettings(
            source=DatasetSource(str(rendered)), out=tmp_path / "exact", swarm="auc-exact", **common
        ),  # type: ignore[arg-type]
        LocalDeployment.for_run(tmp_path / "exact"),
    )

    preset = get_preset("paper")
    trajectory = read_trajectory(rendered / "groundtruth.txt")
    exact_seq = as_on_the_wire(read_constellations(rendered, COCO_NAMES))
    pixel_seq = as_on_the_wire(read_constellations(tmp_path / "pixels" / "detections", COCO_NAMES))
    same_truth = ground_truth(exact_seq, trajectory, exclusion=preset.exclusion).closures
    pixel_matrix = score_decentralized(pixel_seq, ROBOTS, preset).matrix.dense()
    pixel_auc_exact_truth = precision_recall(pixel_matrix, same_truth).auc
    d = pixels.detector
    assert d is not None and pixels.auc is not None and exact.auc is not None
    figures = {
        "frames": FRAMES,
        "robots": ROBOTS,
        "auc_pixels": pixels.auc,
        "auc_pixels_on_exact_ground_truth": pixel_auc_exact_truth,
        "auc_exact": exact.auc,
        "objects_per_frame_pixels": d.objects_per_frame,
        "objects_per_frame_exact": sum(len(c) for c in exact_seq.constellations) / len(exact_seq),
        "loop_closures_pixels": pixels.loop_closures.count,
        "loop_closures_exact": exact.loop_closures.count,
        "model": d.model,
        "conf_threshold": d.conf_threshold,
        "detector_ms": d.stage_ms_mean,
    }
    print(json.dumps(figures, indent=1))

    assert d.frames == FRAMES and d.skipped == {}
    assert (
        pixels.offline_check is not None and pixels.offline_check.identical is True
    )  # what the detectors made
    assert exact.offline_check is not None and exact.offline_check.identical is True
    assert pixel_auc_exact_truth >= exact.auc - MARGIN
    assert pixels.auc > 0.5  # on its own, shallower truth: reported, and far better than chance
