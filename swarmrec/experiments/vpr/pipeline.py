"""Full-image place recognition through a swarm: the pipeline behind ``swarmrec run --method``.

``main(settings, swarm_at)`` wires the stages (docs/vpr.md, "The live swarm")::

    prepare   the descriptor model (checked before anything is rendered), the RGB-D frames
              (rendered with --from-pixels, or a TUM folder with --rgbd; the places
              pipeline's :func:`~swarmrec.experiments.places.pixels.prepare_pixels`), the
              k-means centres (the shipped ones, or trained for this run's k when the
              shipped file lacks it) and the assignment table
    deploy    a router, and on each robot a verifier, a place-owner and a detector in rgbd
              mode with place_method dvpr (workload ``dvpr``): local processes, or a compose
              swarm composed for the run (:mod:`.keep`; the detectors' data folders are
              bind mounts there, read back as a local run's)
    replay    one frame at a time in the simulation's arrival order (lock-step), or free
    collect   the services' counters, the loop closures, the detectors' descriptors
    report    :mod:`.report`

``--method both`` then runs the constellation method on the same rendered frames
(:func:`swarmrec.experiments.places.main` with ``--rgbd`` on the folder, in its own swarm:
the two methods share the verifiers' VerifyRequest/VerifyReply message types, so only
separate swarms measure each one's bytes, load and latency without the other's) and writes
the side-by-side (``comparison.json``).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.deployments.base import Deployment, SwarmSpec, running
from swarmrec.deployments.metrics import Scrape
from swarmrec.errors import ConfigError
from swarmrec.experiments.places import main as places_main
from swarmrec.experiments.places.pixels import PixelSource, prepare_pixels, rgbd_settings
from swarmrec.experiments.places.report import DetectorFigures, PlacesSummary
from swarmrec.experiments.vpr.replay import (
    PlaceReplay,
    TableChange,
    collect_loop_closures,
    rebalance,
    replay_free,
    replay_ordered,
)
from swarmrec.experiments.vpr.report import (
    Comparison,
    DvprSummary,
    RunData,
    compare,
    ground_truth,
    write_report,
)
from swarmrec.experiments.vpr.settings import VprRunSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.vpr.centres import CentresSettings
from swarmrec.vpr.centres import main as train_centres_main
from swarmrec.vpr.clusters import Assignment, load_centres
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.model import DescriptorModel
from swarmrec.vpr.table import SwarmTable, default_centres_path, swarm_table

__all__ = ["BothSummary", "main", "read_descriptors", "resolve_centres", "spec_for"]

Float32Array = npt.NDArray[np.float32]


@dataclass(frozen=True, eq=False)
class BothSummary:
    """``--method both``: each method's summary and the side-by-side."""

    dvpr: DvprSummary
    constellations: PlacesSummary
    comparison: Comparison


def _has_k(path: Path, k: int) -> bool:
    try:
        load_centres(path, k)
    except StateFileError:
        return False
    return True


def resolve_centres(settings: VprRunSettings, say: Callable[[str], None] = lambda _text: None) -> Path:
    """The centres file for this run's k: the one given (which must hold k), else the shipped
    one when it holds k, else ``OUT/centres.npz``, trained now for k when it does not hold it
    yet (:mod:`swarmrec.vpr.centres`: k-means on other worlds, about a minute)."""
    s = settings.dvpr
    robots = settings.run.robots
    k = Assignment.load(s.assignment).n_clusters if s.assignment else robots * s.clusters_per_robot
    if s.centres is not None:
        load_centres(s.centres, k)  # a clear error when the given file lacks k
        return s.centres
    shipped = default_centres_path()
    if _has_k(shipped, k):
        return shipped
    cached = settings.out / "centres.npz"
    if _has_k(cached, k):
        return cached
    say(f"training k-means centres for k = {k} (the shipped ones have other k) into {cached}: about a minute")
    model = Path(s.descriptor_model) if s.descriptor_model else None
    train_centres_main(CentresSettings(out=cached, model=model, ks=(k,)))
    return cached


def spec_for(settings: VprRunSettings, px: PixelSource, centres: Path) -> SwarmSpec:
    """The swarm of a full-image run on ``px``'s frames."""
    run = settings.run
    places = PlaceSettings(preset=run.preset, n_labels=len(px.label_names), wire_positions=run.wire_positions)
    detector = DetectorSettings(detector_mode="rgbd", dataset=str(px.folder), labels_file=px.labels_file)
    parts = (places, detector, rgbd_settings(px, run.pixels), settings.dvpr.component(centres))
    return SwarmSpec(run.bus(), WORKLOADS["dvpr"], parts, workload="dvpr")


def read_descriptors(data_dir: Path, px: PixelSource, blocks: list[range]) -> Float32Array | None:
    """The descriptors the detectors wrote (``robot<r>/detector/descriptors/<frame id>.npy``)
    in frame order; None when one is missing (a skipped frame)."""
    rows = []
    for robot, block in enumerate(blocks):
        folder = data_dir / f"robot{robot}" / "detector" / "descriptors"
        for g in block:
            path = folder / f"{px.frame_ids[g]}.npy"
            if not path.is_file():
                return None
            rows.append(np.load(path, allow_pickle=False).astype(np.float32))
    return np.stack(rows) if rows else None


def _detector_figures(px: PixelSource, metrics: Scrape) -> DetectorFigures:
    outcomes = {
        k: int(v) for k, v in sorted(metrics.by_label("swarmrec_detector_frames_total", "outcome").items())
    }
    sums = metrics.by_label("swarmrec_detector_stage_seconds_sum", "stage")
    counts = metrics.by_label("swarmrec_detector_stage_seconds_count", "stage")
    made = outcomes.get("detected", 0) + outcomes.get("no_objects", 0)
    objects = metrics.total("swarmrec_detector_objects_total")
    return DetectorFigures(
        mode="rgbd",
        folder=str(px.folder),
        model=str(px.model),
        conf_threshold=px.conf_threshold,
        camera=asdict(px.camera),
        frames_without_constellation=0,
        render=px.render,
        frames=sum(outcomes.values()),
        frames_by_outcome=outcomes,
        skipped={k: v for k, v in outcomes.items() if k not in ("detected", "no_objects")},
        boxes_dropped={
            k: int(v) for k, v in metrics.by_label("swarmrec_detector_boxes_dropped_total", "reason").items()
        },
        objects=int(objects),
        objects_per_frame=objects / made if made else 0.0,
        stage_ms_mean={k: 1e3 * sums[k] / counts[k] for k in sorted(sums) if counts.get(k)},
    )


def _refuse(deployment: Deployment) -> Path:
    """Where the deployment's detectors write descriptors; ConfigError for a deployment the
    full-image run cannot read them from, or whose links it cannot drive."""
    if deployment.local_data_dir is None:
        raise ConfigError(
            "a full-image run reads the detectors' descriptors from their data folders on this machine, "
            f"which {deployment.description} does not give (local processes, a compose swarm of the dvpr "
            "workload and a Kubernetes run do)"
        )
    if deployment.emulated_links is not None:
        raise ConfigError("emulated links (--link-*) are not wired into --method dvpr yet")
    if deployment.mesh is not None:
        raise ConfigError(
            "the mesh topology (a router per robot) is not wired into --method dvpr yet: docs/mesh.md"
        )
    return deployment.local_data_dir


def run_dvpr(
    settings: VprRunSettings,
    px: PixelSource,
    centres: Path,
    table: SwarmTable,
    out: Path,
    deployment: Deployment,
    *,
    swarm_hook: Callable[[Deployment], None] | None = None,
    replayed_hook: Callable[[Deployment], None] | None = None,
    timings: dict[str, float] | None = None,
) -> DvprSummary:
    """Deploy the full-image swarm on ``px``'s frames, replay, collect and report into ``out``.
    ``swarm_hook`` sees the swarm once it is up, ``replayed_hook`` once the replay and its
    collection are done, before it stops (tests look at the swarm there)."""
    run = settings.run
    timings = dict(timings or {})
    spec = spec_for(settings, px, centres)
    blocks = split_frames(len(px), run.robots)
    data_dir = _refuse(deployment)
    t_start = time.perf_counter()
    with (
        running(
            deployment,
            spec,
            progress=run.progress,
            timings=timings,
            held_data="start it afresh",
            request_timeout_s=run.request_timeout_s,
        ) as session,
        deployment.client(run.request_timeout_s) as client,
    ):
        if swarm_hook is not None:
            swarm_hook(deployment)
        step_timeout = 6 * run.request_timeout_s
        result: PlaceReplay
        tables: list[TableChange] = []
        every = settings.dvpr.rebalance_every
        last_step = max(len(b) for b in blocks) - 1

        def after_step(t: int, sent: int) -> None:
            # Between steps, no frame in flight: the swarm moves, then the next step routes by it.
            if every and (t + 1) % every == 0 and t < last_step:
                reply = rebalance(client, run.robots, 60 * run.request_timeout_s)
                tables.append(TableChange(sent, t + 1, reply))

        if run.lockstep:
            result = replay_ordered(
                client, blocks, step_timeout, progress=run.progress, after_step=after_step
            )
        else:
            rate = 0.0 if run.pace == "fast" else float(run.pace)
            result = replay_free(client, blocks, rate, step_timeout, progress=run.progress)
        timings["replay_s"] = result.wall_s
        metrics = deployment.metrics()
        closures = collect_loop_closures(client, run.robots, result)
        if replayed_hook is not None:
            replayed_hook(deployment)
    exit_codes = session.exit_codes
    timings["swarm_total_s"] = time.perf_counter() - t_start
    descriptors = read_descriptors(data_dir, px, blocks)
    assignment = table.assignment
    swarm = {
        "robots": run.robots,
        "pace": run.pace,
        "clusters_per_robot": assignment.n_clusters // run.robots,
        "clusters": assignment.n_clusters,
        "assignment": assignment.to_json(),
        "centres": str(centres),
        "centres_sha256": table.digest,
        "wire_code": settings.dvpr.wire_code,
        "min_objects_to_verify": get_preset(run.preset).min_objects,
        "loop_closure_min_score": PlaceSettings().loop_closure_min_score,
        "deployment": deployment.description,
        "processes": len(exit_codes),
        "rebalance_every_steps": settings.dvpr.rebalance_every,
    }
    stamps = np.array([f.timestamp for f in px.frames], dtype=np.float64)
    data = RunData(
        name=px.name,
        folder=str(px.folder),
        blocks=blocks,
        frame_ids=px.frame_ids,
        stamps=stamps,
        trajectory=px.trajectory,
        replay=result,
        closures=closures,
        metrics=metrics,
        router=table.router,
        centres=centres,
        digest=table.digest,
        wire_code=settings.dvpr.wire_code,
        descriptors=descriptors,
        swarm=swarm,
        exit_codes=exit_codes,
        timings=timings,
        lockstep=run.lockstep,
        detector=_detector_figures(px, metrics),
        tables=tables,
    )
    return write_report(out, data, plots=run.plots)


def _places_closures(path: Path, blocks: list[range]) -> list[tuple[int, int]]:
    """The constellation run's loop closures (its ``loop_closures.csv``) as global frames."""
    with path.open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return [
        (
            blocks[int(r["query_robot"])].start + int(r["query_frame"]),
            blocks[int(r["match_robot"])].start + int(r["match_frame"]),
        )
        for r in rows
    ]


def main(
    settings: VprRunSettings,
    swarm_at: Callable[[Path], Deployment],
    *,
    say: Callable[[str], None] = lambda _text: None,
    swarm_hook: Callable[[Deployment], None] | None = None,
    replayed_hook: Callable[[Deployment], None] | None = None,
) -> DvprSummary | BothSummary:
    """Run ``settings.method`` (dvpr, or both one after the other on the same frames); the
    summary is also written under ``settings.out``. ``swarm_at(folder)`` is the deployment
    of the swarm whose report goes to ``folder`` (each method runs in a swarm of its own:
    the two share message types, so only separate swarms measure each one's bytes)."""
    t_start = time.perf_counter()
    out = settings.out
    both = settings.method == "both"
    dvpr_out = out / "dvpr" if both else out
    deployment = swarm_at(dvpr_out)
    _refuse(deployment)  # before minutes of rendering
    out.mkdir(parents=True, exist_ok=True)
    run = settings.run
    # A file that is not a descriptor model stops the run here, before minutes of rendering.
    DescriptorModel(settings.dvpr.descriptor_model or None)
    centres = resolve_centres(settings, say)
    s = settings.dvpr
    table = swarm_table(
        run.robots, s.clusters_per_robot, s.assignment_seed, centres=centres, assignment=s.assignment
    )
    px = prepare_pixels(run)
    timings = {"prepare_s": time.perf_counter() - t_start}
    if px.render is not None:
        timings["render_s"] = float(px.render["total_s"])
    dvpr = run_dvpr(
        settings,
        px,
        centres,
        table,
        dvpr_out,
        deployment,
        swarm_hook=swarm_hook,
        replayed_hook=replayed_hook,
        timings=timings,
    )
    if not both:
        return dvpr
    # The same frames: the folder rendered (or given) above, read by the constellation detectors.
    pixels = replace(run.pixels, from_pixels=False, rgbd=px.folder)
    places_out = out / "constellations"
    places = places_main(run.with_(out=places_out, pixels=pixels), swarm_at(places_out))
    blocks = split_frames(len(px), run.robots)
    truth = None
    if px.trajectory is not None:
        stamps = np.array([f.timestamp for f in px.frames], dtype=np.float64)
        truth = ground_truth(px.trajectory, stamps, blocks)
    closures = _places_closures(out / "constellations" / "loop_closures.csv", blocks)
    comparison = compare(dvpr, places, closures, truth)
    (out / "comparison.json").write_text(json.dumps(asdict(comparison), indent=2) + "\n")
    return BothSummary(dvpr, places, comparison)
