"""Place recognition through a swarm: the pipeline behind ``swarmrec run``.

``main(settings, deployment)`` wires the stages and knows nothing of where the
swarm runs::

    prepare      the dataset (the built-in synthetic world by default) or, from
                 pixels, the RGB-D folder; the label ranges; the swarm's spec
    deploy       deployment.start(spec): local processes by default, or a check
                 that a running compose swarm is this spec (``run --attach``)
    replay       lock-step or paced, through the detectors (:mod:`.replay`)
    collect      the services' counters (deployment.metrics()), the loop closures
    report       pair scores, PR/AUC, bytes, load, the check against the offline
                 evaluation (:mod:`.report`, docs/swarm.md "The main job")

In lock-step mode (the default) step t of every robot finishes before step
t + 1 starts, exactly as the offline decentralized evaluation simulates, and
the report checks that the swarm's pair scores equal the offline ones. From
pixels (``--from-pixels`` renders the synthetic world, ``--rgbd`` names a
TUM-format folder) the detectors detect objects in RGB-D frames instead of
replaying constellations, and the report scores the constellations they made
(:mod:`.pixels`, docs/detector.md).
"""

from __future__ import annotations

import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import zenoh

from swarmrec.client import ZenohClient
from swarmrec.core.association import build_table
from swarmrec.core.presets import Preset, get_preset
from swarmrec.core.ranges import label_bounds
from swarmrec.core.split import split_frames
from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.datasets.constellations import write_constellations
from swarmrec.deployments.base import Deployment, SwarmSpec, running
from swarmrec.errors import ConfigError, WireError
from swarmrec.evaluation.partition import Reach
from swarmrec.evaluation.scoring import label_frequency_prior
from swarmrec.evaluation.source import load_dataset
from swarmrec.experiments.mesh import plan_mesh
from swarmrec.experiments.places.pixels import PixelSource, detected_sequence, prepare_pixels, rgbd_settings
from swarmrec.experiments.places.replay import collect_loop_closures, replay
from swarmrec.experiments.places.report import (
    DetectorFigures,
    LinkReport,
    OfflineEvaluation,
    PlacesSummary,
    RunRecord,
    write_report,
)
from swarmrec.experiments.places.settings import PlacesSettings
from swarmrec.runtime import keys
from swarmrec.runtime.settings import Component
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto, constellation_to_proto, decode

#: How long a run waits after its replay for handoffs and retried stores to finish.
SETTLE_TIMEOUT_S = 60.0
#: ... giving up sooner when only stores are owed and none was acknowledged for this long
#: (their shard died as its group's only owner: the report says how many are pending).
SETTLE_STALL_S = 10.0

__all__ = [
    "SETTLE_TIMEOUT_S",
    "Prepared",
    "as_on_the_wire",
    "main",
    "prepare",
    "swarm_bounds",
]

IntArray = npt.NDArray[np.int64]


def as_on_the_wire(seq: ConstellationSequence, *, exact: bool = False) -> ConstellationSequence:
    """``seq`` as the services see it: positions rounded to the wire's millimetres (unchanged
    when the swarm carries them ``exact``)."""
    if exact:
        return seq
    out = [
        constellation_from_proto(constellation_to_proto(c, 0, 0), seq.n_labels) for c in seq.constellations
    ]
    return ConstellationSequence(
        seq.frame_ids, seq.timestamps, tuple(out), seq.label_names, seq.name, dict(seq.skipped)
    )


def swarm_bounds(preset: Preset, robots: int, n_labels: int, seq: ConstellationSequence | None) -> IntArray:
    """The shards' label ranges for ``preset`` (``balanced`` weighs labels by their
    frequency in ``seq``, which RGB-D frames do not have before detection)."""
    load = None
    if preset.ranges == "balanced":
        if seq is None:
            raise ConfigError(
                "the balanced preset balances label ranges on the dataset's label frequencies, which "
                "RGB-D frames do not have before detection (a synthetic render has them in its "
                "constellations/); use --preset paper"
            )
        load = label_frequency_prior(build_table(seq.constellations, seq.n_labels))
    return label_bounds(preset.ranges, n_labels, robots, load)


@dataclass(frozen=True, eq=False)
class Prepared:
    """The data of a run and the swarm that will replay it."""

    spec: SwarmSpec
    preset: Preset
    bounds: IntArray
    blocks: list[range]
    #: The constellations replayed (None from pixels: they are detected during the run).
    sequence: ConstellationSequence | None
    trajectory: Trajectory | None
    pixels: PixelSource | None


def prepare(settings: PlacesSettings, *, dataset_dir: Path) -> Prepared:
    """Load (or render) the data, choose the label ranges and write the swarm's spec;
    a dataset that is not on disk as the detectors will read it is written to ``dataset_dir``."""
    preset = get_preset(settings.preset)
    parts: list[Component]
    if settings.pixels.enabled:
        px = prepare_pixels(settings)
        n_frames, n_labels = len(px), len(px.label_names)
        bounds = swarm_bounds(preset, settings.robots, n_labels, px.exact)
        detector = DetectorSettings(detector_mode="rgbd", dataset=str(px.folder), labels_file=px.labels_file)
        parts = [detector, rgbd_settings(px, settings.pixels)]
        seq, trajectory = None, px.trajectory
    else:
        px = None
        data = load_dataset(settings.source, materialize=dataset_dir)
        seq, trajectory = data.sequence, data.trajectory
        n_frames, n_labels = len(seq), seq.n_labels
        bounds = swarm_bounds(preset, settings.robots, n_labels, seq)
        assert data.folder is not None  # materialized
        parts = [
            DetectorSettings(detector_mode="replay", dataset=str(data.folder), labels_file=data.labels_file)
        ]
    places = settings.places(n_labels, tuple(int(b) for b in bounds))
    spec = SwarmSpec(settings.bus(), WORKLOADS["places"], (places, settings.index, *parts), workload="places")
    return Prepared(spec, preset, bounds, split_frames(n_frames, settings.robots), seq, trajectory, px)


def _offline(seq: ConstellationSequence, prepared: Prepared, reach: Reach | None = None) -> OfflineEvaluation:
    """The offline evaluation of ``seq`` as the run's swarm saw it (``reach``: a mesh's team
    that split and healed, simulated on the same schedule)."""
    places = prepared.spec.component(PlaceSettings)
    assert isinstance(places, PlaceSettings)
    wire_seq = as_on_the_wire(seq, exact=places.exact_positions)
    return OfflineEvaluation(
        seq, wire_seq, prepared.trajectory, prepared.preset, prepared.bounds, prepared.spec.robots, reach
    )


def _link_schedule(
    deployment: Deployment, client: ZenohClient, events: list[tuple[float, str]]
) -> Callable[[int], None] | None:
    """What puts the links in the schedule's state before each lock-step step (or, for a
    schedule in seconds, a timer thread); every change is recorded in ``events``. In
    lock-step, a robot back in range is waited for (its services reconnect in a second
    or two) before the step goes on, so it misses exactly the steps it was out."""
    links = deployment.emulated_links
    if links is None or links.schedule is None:
        return None
    schedule = links.schedule
    if schedule.unit == "step":

        def before(t: int) -> None:
            changed = links.apply_links(float(t))
            events.extend((float(t), e) for e in changed)
            back = {int(e.split()[1]) for e in changed if e.endswith("back in range")}
            if back:
                client.wait_for(links.services_of(back), 60.0)

        return before
    start = time.monotonic()

    def follow() -> None:
        for t in schedule.changes():
            delay = start + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            events.extend((t, e) for e in links.apply_links(t))

    threading.Thread(target=follow, name="link-schedule", daemon=True).start()
    return None


def _refuse(settings: PlacesSettings, deployment: Deployment) -> None:
    """Settings this deployment cannot honour, refused before anything is written or started."""
    if settings.pixels.enabled and deployment.local_data_dir is None:
        raise ConfigError("a run from pixels reads the detectors' constellations from a local deployment")
    links = deployment.emulated_links
    stepped = links is not None and links.schedule is not None and links.schedule.unit == "step"
    if stepped and not settings.lockstep:
        raise ConfigError("a schedule in steps needs a lock-step replay; give its times in seconds")


def _drain_placement_changes(sub: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]]) -> list[pb.PlacementChange]:
    """The PlacementChange events the subscriber holds; one that does not decode is left out
    (the report's history is what the coordinators said, never a guess)."""
    out = []
    while (sample := sub.try_recv()) is not None:
        try:
            out.append(decode(sample.payload.to_bytes(), pb.PlacementChange))
        except WireError:
            continue
    return out


def main(
    settings: PlacesSettings,
    deployment: Deployment,
    *,
    on_step: Callable[[int], None] | None = None,
    swarm_hook: Callable[[Deployment], None] | None = None,
    after_replay: Callable[[Deployment], None] | None = None,
) -> PlacesSummary:
    """Run the swarm on ``deployment``, write the report, return the summary.

    ``on_step`` is called after each lock-step step, ``swarm_hook`` once the swarm is
    up and ``after_replay`` once the replay is over and the index has settled, while
    the swarm still runs (tests use them to inject faults and look inside).
    """
    t_start = time.perf_counter()
    out = settings.out
    _refuse(settings, deployment)
    out.mkdir(parents=True, exist_ok=True)
    prepared = prepare(settings, dataset_dir=out / "dataset")
    # A mesh's radio graph, from the robots' positions: a bad schedule is refused now.
    mesh = plan_mesh(deployment, prepared.blocks, prepared.trajectory, lockstep=settings.lockstep)
    spec = prepared.spec
    timings: dict[str, float] = {"prepare_s": time.perf_counter() - t_start}
    offline: OfflineEvaluation | None = None
    afresh = "start it afresh (swarmrec down, then up; for compose: swarmrec compose down, then up)"
    with (
        running(
            deployment,
            spec,
            progress=settings.progress,
            timings=timings,
            held_data=afresh,
            request_timeout_s=settings.request_timeout_s,
        ) as session,
        # The operator identity: it drives the replay (detector step/replay).
        deployment.client(settings.request_timeout_s) as client,
        # The index coordinator says why each placement came: the report's history of them.
        client.session.declare_subscriber(keys.event(spec.bus.swarm, "placement", "*")) as placements,
    ):
        # Every robot's shard confirmed on one settled placement before the first
        # frame: in a big swarm started at once, a shard that comes up after the
        # coordinator's first placement waits for it to be confirmed and refuses
        # stores meanwhile; those slices would be stored after their step (a
        # 50-robot swarm lost the lock-step identity so). Part of the start time.
        t0 = time.perf_counter()
        # (A swarm of fixed size has a shard on every robot; elsewhere the operator may
        # have scaled them, so only the placement's own members are waited for.)
        every = deployment.fixed_size and "index-shard" in spec.kinds
        client.wait_index_settled(timeout_s=SETTLE_TIMEOUT_S, shards=spec.bus.n_robots if every else None)
        timings["index_ready_s"] = time.perf_counter() - t0
        timings["start_s"] += timings["index_ready_s"]
        if swarm_hook is not None:
            swarm_hook(deployment)
        link_events: list[tuple[float, str]] = []
        before_step = _link_schedule(deployment, client, link_events)
        if mesh is not None:
            before_step = mesh.before_step(client)  # type: ignore[arg-type]  # a mesh's operator
            mesh.start_counting()
        result = replay(client, prepared.blocks, settings.replay(), on_step, before_step)
        timings["replay_s"] = result.wall_s
        # A team that split: the offline simulation of the same connectivity schedule.
        reach = mesh.reach(prepared.bounds.tolist(), settings.index.replicas) if mesh is not None else None
        if prepared.sequence is not None:  # (from pixels: the detections, read after the stop)
            checking = _offline(prepared.sequence, prepared, reach)
            offline = checking.start(check_offline=settings.check_offline)
        # Handoffs and retried stores finish before anything is counted, so the report
        # agrees with what the shards hold.
        t0 = time.perf_counter()
        index_state = client.wait_index_settled(timeout_s=SETTLE_TIMEOUT_S, stall_s=SETTLE_STALL_S)
        timings["settle_s"] = time.perf_counter() - t0
        # The history up to the placement the report describes: a coordinator may publish
        # another after it (it does not know the replay is over).
        final = index_state.placement.version if index_state.placement is not None else -1
        placement_changes = [c for c in _drain_placement_changes(placements) if c.version <= final]
        mesh_figures = mesh.report(len(result.reports)) if mesh is not None else None
        if after_replay is not None:
            after_replay(deployment)
        t0 = time.perf_counter()
        metrics = deployment.metrics()
        timings["scrape_s"] = time.perf_counter() - t0
        closures = collect_loop_closures(client, settings.robots, result)
    exit_codes = session.exit_codes
    seq, detector = prepared.sequence, None
    if prepared.pixels is not None:
        px = prepared.pixels
        data_dir = deployment.local_data_dir
        assert data_dir is not None  # refused before the run
        seq, not_made = detected_sequence(px, data_dir, prepared.blocks)
        shutil.rmtree(out / "detections", ignore_errors=True)
        write_constellations(seq, out / "detections")
        detector = DetectorFigures(
            mode="rgbd",
            folder=str(px.folder),
            model=str(px.model),
            conf_threshold=px.conf_threshold,
            camera=asdict(px.camera),
            frames_without_constellation=len(not_made),
            render=px.render,
        )
        if px.render is not None:
            timings["render_s"] = px.render["total_s"]
    assert seq is not None
    timings["total_s"] = time.perf_counter() - t_start
    places = spec.component(PlaceSettings)
    assert isinstance(places, PlaceSettings)
    replayed = spec.component(DetectorSettings)
    assert isinstance(replayed, DetectorSettings)
    offline = offline or _offline(seq, prepared, reach)
    record = RunRecord(
        seq=seq,
        offline=offline,
        trajectory=prepared.trajectory,
        preset=prepared.preset,
        bounds=prepared.bounds,
        blocks=prepared.blocks,
        replay=result,
        metrics=metrics,
        closures=closures,
        exit_codes=exit_codes,
        timings=timings,
        deployment=deployment.description,
        loop_closure_min_score=places.loop_closure_min_score,
        index=index_state,
        placement_changes=placement_changes,
        detector=detector,
        # From pixels the constellations are the detections written back above.
        dataset_folder=out / "detections" if prepared.pixels is not None else Path(replayed.dataset),
        labels_file=replayed.labels_file,
        links=_link_report(deployment, link_events),
        mesh=mesh_figures,
    )
    return write_report(settings.report(), record)


def _link_report(deployment: Deployment, events: list[tuple[float, str]]) -> LinkReport | None:
    links = deployment.emulated_links
    if links is None:
        return None
    unit = links.schedule.unit if links.schedule is not None else "step"
    return LinkReport(links.link.rate_kbps, links.link.latency_ms, unit, sorted(events))
