"""The landmark swarm simulation: a street of 19 landmarks, robots that classify what
they face, and cooperative recognition over the real bus (Brent, Yuan and Stegagno's
experiment, Sec. 4).

One command (``swarmrec landmarks``) does what the paper's Gazebo runs did::

    street configurations (swarmrec.fusion.street: 2-4 clusters, line / double line / free,
    varied yaw, a connected radio graph)
        --> each robot's view rendered (swarmrec.fusion.facades), PNG-encoded
        --> detector/<i>/classify (classifier mode: the CNN on onnxruntime)
        --> fusion/<i>/start_round with this round's neighbours
        --> flooding over zenoh, robot to neighbour, Eq. 12 after every new origin
        --> fusion/<i>/posterior once the round is quiet: the decision after each message

A configuration is run once per weight law, each law its own round, on the same
views (the flooding does not depend on the law, the fusion does). A round is over
for robot ``i`` when it has received every copy Algorithm 1 sends it: its ``n - 1``
new origins plus the duplicates, ``n * deg(i)`` deliveries in all, as
:func:`~swarmrec.fusion.flooding.simulate_flooding` counts them. Only then does the
next round start, so no copy of a finished round is left to be mistaken for
a late one.

The robots run on any deployment (local processes by default, a detector and a
fusion service per robot, one zenoh router; or a compose swarm); the views are
rendered here and reach each robot's detector as a request, as a camera frame would.
Every robot's recorded history is checked against
:class:`~swarmrec.fusion.wnbc.FusionState` recomputed from the same vectors in the
same order, so the report says whether the services computed what the equations say.
:mod:`.report` turns the records into the paper's figures.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from swarmrec.client import ZenohClient
from swarmrec.deployments.base import Deployment, SwarmSpec, running
from swarmrec.deployments.metrics import Scrape
from swarmrec.errors import CallError, ConfigError, ErrorCode, RemoteError
from swarmrec.fusion.facades import RenderSettings, View, render_view
from swarmrec.fusion.flooding import FloodResult, simulate_flooding
from swarmrec.fusion.street import StreetSettings, SwarmConfiguration, default_street, generate_configurations
from swarmrec.fusion.wnbc import (
    N_LANDMARKS,
    WEIGHT_LAWS,
    AgreementWeightLaw,
    FusionState,
    PaperWeightLaw,
    WeightLaw,
    make_weight_law,
)
from swarmrec.runtime import keys
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import ClassifierSettings, DetectorSettings
from swarmrec.services.settings import LandmarkSettings as ClassSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.fusion import weight_law_to_proto

__all__ = [
    "DEFAULT_LAWS",
    "VIEW_PRESETS",
    "LandmarkSettings",
    "LawChoice",
    "RobotRound",
    "SimulationResult",
    "check_against_core",
    "expected_deliveries",
    "parse_law",
    "reference_flood",
    "render_views",
    "run_simulation",
    "swarm_spec",
]

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LawChoice:
    """A weight law to compare: ``paper`` with its lambda (Eq. 16) or ``agreement``."""

    name: str
    lam: float | None = None

    def __post_init__(self) -> None:
        self.law()  # unknown names and bad lambdas fail here, before any process starts

    @property
    def key(self) -> str:
        """``paper:2``, ``agreement``: how the CLI and the report's files name it."""
        return self.name if self.lam is None else f"{self.name}:{self.lam:g}"

    @property
    def label(self) -> str:
        """How a figure's legend names it (with the lambda the law really uses)."""
        law = self.law()
        if isinstance(law, AgreementWeightLaw):
            return f"adaptive (agreement, prior λ = {law.prior.lam:g})"
        assert isinstance(law, PaperWeightLaw)  # the two laws make_weight_law knows
        return f"paper, λ = {law.lam:g}"

    def law(self) -> WeightLaw:
        return make_weight_law(self.name, lam=self.lam)

    def to_proto(self) -> pb.WeightLaw:
        return weight_law_to_proto(self.name, self.lam)


def parse_law(text: str) -> LawChoice:
    """``paper:1`` -> LawChoice("paper", 1.0); ``agreement`` -> its default prior."""
    name, _, lam = text.strip().partition(":")
    if name not in WEIGHT_LAWS:
        raise ConfigError(f"unknown weight law {name!r} in {text!r}; laws: {', '.join(WEIGHT_LAWS)}")
    try:
        value = float(lam) if lam else None
    except ValueError:
        raise ConfigError(f"lambda of {text!r} is not a number") from None
    return LawChoice(name, value)


#: The paper's four lambdas (Fig. 3) and the adaptive law.
DEFAULT_LAWS: tuple[LawChoice, ...] = (
    LawChoice("paper", 0.0),
    LawChoice("paper", 1.0),
    LawChoice("paper", 2.0),
    LawChoice("paper", 100.0),
    LawChoice("agreement"),
)

#: How hard the robots' views are. ``nominal``: the nuisances the CNN was trained on
#: (its held-out accuracy, about 92 %). ``harsh``: every view occluded, darker and
#: noisier, which brings the single robot near the paper's 68 % in the swarm.
VIEW_PRESETS: dict[str, RenderSettings] = {
    "nominal": RenderSettings(),
    "harsh": RenderSettings(
        occlusion=1.0, noise=(20.0, 45.0), light=(0.25, 1.7), blur=0.9, colour_jitter=45.0, tilt=0.25
    ),
}


@dataclass(frozen=True)
class LandmarkSettings:
    """What ``swarmrec landmarks`` runs (defaults: the paper's 118 configurations of 10 robots)."""

    out: Path
    configurations: int = 118
    robots: int = 10
    seed: int = 0
    laws: tuple[LawChoice, ...] = DEFAULT_LAWS
    views: str = "nominal"
    radio_range: float = 7.0
    #: The classifier's ONNX file; "" is the shipped models/landmarks/landmark_cnn.onnx.
    model: str = ""
    #: Longest wait for one round's flooding to go quiet before it is recorded as incomplete.
    round_timeout_s: float = 20.0
    request_timeout_s: float = 10.0
    swarm: str = "landmarks"
    progress: bool = True

    def __post_init__(self) -> None:
        problems = []
        if self.configurations < 1:
            problems.append(f"configurations must be >= 1, got {self.configurations}")
        if not 2 <= self.robots <= 64:
            problems.append(f"robots must be 2 to 64, got {self.robots}")
        if not self.laws:
            problems.append("give at least one weight law")
        if len({law.key for law in self.laws}) != len(self.laws):
            problems.append(f"weight laws repeat: {[law.key for law in self.laws]}")
        if self.views not in VIEW_PRESETS:
            problems.append(f"views must be one of {', '.join(VIEW_PRESETS)}, got {self.views!r}")
        if not self.round_timeout_s > 0 or not self.request_timeout_s > 0:
            problems.append("timeouts must be > 0")
        if problems:
            raise ConfigError("landmark simulation: " + "; ".join(problems))
        self.street_settings()  # radio range and robots checked by the street's own rules

    def with_(self, **changes: object) -> LandmarkSettings:
        """A copy with some settings changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]

    def street_settings(self) -> StreetSettings:
        max_clusters = min(4, self.robots)
        return StreetSettings(
            n_robots=self.robots,
            radio_range=self.radio_range,
            min_clusters=min(2, max_clusters),
            max_clusters=max_clusters,
        )


@dataclass
class RobotRound:
    """One robot's part of one round: what it saw, what it decided after each message."""

    configuration: int
    law: str
    robot: int
    truth: int
    #: Its own classifier output, as it went on the wire (float32 values).
    probabilities: list[float]
    #: Decision after 0, 1, ... incorporated messages (index 0: its own view alone).
    decisions: list[int]
    #: (origin, hops, yaw, weight) of each incorporated message, in order.
    history: list[tuple[int, int, float, float]]
    posterior: list[float]
    duplicates: int
    rejected: int
    #: Deliveries Algorithm 1 sends it, and whether all arrived before the round ended.
    expected_deliveries: int
    complete: bool
    #: Largest difference between its posterior and the core's recomputation (None: not checked).
    core_difference: float | None = None

    @property
    def incorporated(self) -> int:
        return len(self.history)


@dataclass
class SimulationResult:
    settings: LandmarkSettings
    configurations: list[SwarmConfiguration]
    rounds: list[RobotRound]
    #: The fusion services' counters, scraped at the end (bytes per message type ...).
    metrics: Scrape
    timings: dict[str, float]
    errors: list[str] = field(default_factory=list)
    #: Classify calls that failed, by reason.
    failures: dict[str, int] = field(default_factory=dict)


def render_views(
    configurations: Sequence[SwarmConfiguration], seed: int, settings: RenderSettings
) -> list[ImageArray]:
    """Each configuration's robots' views, ``[n_robots, 64, 64, 3]`` RGB, each from its own
    stream ``(seed, configuration, robot)`` so it does not depend on what else is rendered."""
    out = []
    for c in configurations:
        views = [
            render_view(
                int(c.landmarks[i]),
                View(float(c.distances[i]), float(c.view_angles[i]), float(c.offsets[i])),
                np.random.default_rng([seed, c.index, i]),
                settings,
            )
            for i in range(c.n_robots)
        ]
        out.append(np.stack(views))
    return out


def reference_flood(config: SwarmConfiguration) -> FloodResult:
    """Algorithm 1 on the configuration's graph in the core's synchronous steps (the
    vectors do not matter here): what every round must deliver, and at which hop
    counts a breadth-first delivery would arrive."""
    n = config.n_robots
    return simulate_flooding(config.adjacency, np.full((n, 2), 0.5), np.zeros(n))


def expected_deliveries(config: SwarmConfiguration) -> list[int]:
    """How many copies Algorithm 1 delivers to each robot in one round (own-origin copies
    included): every neighbour broadcasts its own message and one forward per other origin."""
    counts = [0] * config.n_robots
    for _step, _sender, receiver, _origin in reference_flood(config).deliveries:
        counts[receiver] += 1
    return counts


def check_against_core(
    record: RobotRound, probabilities: Sequence[Sequence[float] | None], yaws: Sequence[float], law: WeightLaw
) -> float | None:
    """The largest difference between a robot's reported posterior and Eq. 12 recomputed by
    the core (:class:`FusionState`) from the same vectors (``probabilities[j]``: robot
    ``j``'s output as sent) in the robot's own order; ``inf`` when a decision after some
    message differs, None when a vector it heard is unknown (that robot's reply was lost)."""
    if probabilities[record.robot] is None or any(probabilities[o] is None for o, *_ in record.history):
        return None
    state = FusionState(
        np.asarray(probabilities[record.robot]), float(yaws[record.robot]), law, own_id=record.robot
    )
    if state.decision != record.decisions[0]:
        return math.inf
    for k, (origin, hops, yaw, _weight) in enumerate(record.history, start=1):
        state.incorporate(origin, np.asarray(probabilities[origin]), hops, yaw)
        if state.decision != record.decisions[k]:
            return math.inf
    return float(np.abs(state.posterior - np.asarray(record.posterior)).max())


def _encode_png(image: ImageArray) -> bytes:
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 BGR image
        raise RuntimeError("PNG encoding failed")
    return bytes(data.tobytes())


class _Runner:
    """Runs rounds against a live swarm through one client session."""

    def __init__(self, client: ZenohClient, settings: LandmarkSettings) -> None:
        self.client = client
        self.s = settings
        self.pool = ThreadPoolExecutor(max_workers=settings.robots)
        self.failures: dict[str, int] = {}
        self.errors: list[str] = []

    def _classify(self, robot: int, request: pb.ClassifyRequest) -> pb.ClassifyReply | None:
        key = keys.endpoint(self.s.swarm, "detector", robot, "classify")
        try:
            reply: pb.ClassifyReply = self.client.call(
                key, request, pb.ClassifyReply, target_robot=robot, endpoint="classify"
            )
            return reply
        except CallError as e:
            reason = getattr(e, "reason", "error")
            self.failures[reason] = self.failures.get(reason, 0) + 1
            self.errors.append(f"round {request.round_id} robot {robot}: {e}")
            return None

    def _posterior(self, robot: int, round_id: int) -> pb.FusionPosterior | None:
        key = keys.endpoint(self.s.swarm, "fusion", robot, "posterior")
        try:
            reply: pb.FusionPosterior = self.client.call(
                key, pb.PosteriorRequest(round_id=round_id), pb.FusionPosterior, target_robot=robot
            )
            return reply
        except CallError as e:
            self.errors.append(f"posterior of robot {robot} round {round_id}: {e}")
            return None

    def round(
        self,
        round_id: int,
        config: SwarmConfiguration,
        views: list[bytes],
        law: LawChoice,
        expected: list[int],
    ) -> list[RobotRound]:
        n = config.n_robots
        requests = [
            pb.ClassifyRequest(
                round_id=round_id,
                image=views[i],
                yaw_rad=float(config.yaws[i]),
                neighbour_robot_ids=np.flatnonzero(config.adjacency[i]).tolist(),
                weight_law=law.to_proto(),
            )
            for i in range(n)
        ]
        replies = list(self.pool.map(self._classify, range(n), requests))
        deadline = time.monotonic() + self.s.round_timeout_s
        posteriors: list[pb.FusionPosterior | None] = [None] * n
        pending = {i for i in range(n) if replies[i] is not None}
        pause = 0.002
        while pending:
            for i, post in zip(
                sorted(pending),
                self.pool.map(lambda r: self._posterior(r, round_id), sorted(pending)),
                strict=True,
            ):
                posteriors[i] = post
                if post is not None and post.incorporated + post.duplicates >= expected[i]:
                    pending.discard(i)
            if not pending or time.monotonic() > deadline:
                break
            time.sleep(pause)
            pause = min(pause * 2, 0.05)
        records = []
        for i in range(n):
            reply, post = replies[i], posteriors[i]
            if reply is None or post is None:
                continue
            history = [(s.origin_robot_id, s.hops, float(s.yaw_rad), s.weight) for s in post.history]
            records.append(
                RobotRound(
                    configuration=config.index,
                    law=law.key,
                    robot=i,
                    truth=int(config.landmarks[i]),
                    probabilities=list(reply.probabilities),
                    decisions=[int(reply.decision)] + [s.decision_after for s in post.history],
                    history=history,
                    posterior=list(post.posterior),
                    duplicates=post.duplicates,
                    rejected=post.rejected,
                    expected_deliveries=expected[i],
                    complete=i not in pending,
                )
            )
        return records

    def close(self) -> None:
        self.pool.shutdown()


def _run_rounds(
    s: LandmarkSettings,
    deployment: Deployment,
    configs: Sequence[SwarmConfiguration],
    encoded: Sequence[list[bytes]],
    timings: dict[str, float],
    on_round: Callable[[int, int], None] | None,
) -> tuple[_Runner, list[RobotRound]]:
    """Every (configuration, law) round through ``deployment``'s swarm, as its operator."""
    rounds: list[RobotRound] = []
    with deployment.client(s.request_timeout_s) as client:
        runner = _Runner(client, s)
        try:
            first = _last_round(runner, s.robots)
            total = len(configs) * len(s.laws)
            t2 = time.perf_counter()
            with tqdm(total=total, desc="rounds", disable=not s.progress, leave=False) as bar:
                done = 0
                for config, views in zip(configs, encoded, strict=True):
                    expected = expected_deliveries(config)
                    for law in s.laws:
                        done += 1
                        rounds += runner.round(first + done, config, views, law, expected)
                        bar.update(1)
                        if on_round is not None:
                            on_round(done, total)
            timings["rounds_s"] = time.perf_counter() - t2
        except BaseException:
            runner.close()
            raise
    return runner, rounds


def _last_round(runner: _Runner, robots: int) -> int:
    """The highest round any fusion service already started (0 for fresh ones): a swarm
    that ran an earlier simulation refuses round ids that do not increase."""
    last = 0
    for robot in range(robots):
        key = keys.endpoint(runner.s.swarm, "fusion", robot, "posterior")
        try:
            reply = runner.client.call(key, pb.PosteriorRequest(), pb.FusionPosterior, target_robot=robot)
            last = max(last, reply.round_id)
        except RemoteError as e:
            if e.code != ErrorCode.NOT_FOUND:  # NOT_FOUND: no round yet
                raise
    return last


def swarm_spec(s: LandmarkSettings) -> SwarmSpec:
    """The swarm of the simulation: per robot, a detector in classifier mode and a fusion service."""
    bus = BusSettings(swarm=s.swarm, n_robots=s.robots, request_timeout_s=s.request_timeout_s)
    parts = (
        DetectorSettings(detector_mode="classifier"),
        ClassifierSettings(classifier_model=s.model),
        ClassSettings(n_classes=N_LANDMARKS),
    )
    return SwarmSpec(bus, WORKLOADS["landmarks"], parts, workload="landmarks")


def run_simulation(
    settings: LandmarkSettings,
    deployment: Deployment,
    *,
    on_round: Callable[[int, int], None] | None = None,
    swarm_hook: Callable[[Deployment], None] | None = None,
) -> SimulationResult:
    """Generate, render, run every (configuration, law) round on ``deployment`` (stopped at
    the end), check against the core.

    ``on_round(done, total)`` reports progress; ``swarm_hook`` runs once the swarm is up
    (tests use it to disturb the swarm)."""
    t0 = time.perf_counter()
    s = settings
    configs = generate_configurations(
        s.configurations, seed=s.seed, settings=s.street_settings(), street=default_street()
    )
    images = render_views(configs, s.seed, VIEW_PRESETS[s.views])
    encoded = [[_encode_png(img) for img in views] for views in images]
    timings = {"prepare_s": time.perf_counter() - t0}
    rounds: list[RobotRound] = []
    metrics = Scrape()
    runner: _Runner | None = None
    with running(deployment, swarm_spec(s), progress=s.progress, timings=timings):
        if swarm_hook is not None:
            swarm_hook(deployment)
        try:
            runner, rounds = _run_rounds(s, deployment, configs, encoded, timings, on_round)
            metrics = deployment.metrics()
        finally:
            if runner is not None:
                runner.close()  # before the swarm stops
    # The check against the core: same vectors (float32 from the wire), same order.
    laws = {law.key: law.law() for law in s.laws}
    # Yaws as the wire carried them (float32), as the services used them.
    yaws = {c.index: c.yaws.astype(np.float32).astype(np.float64).tolist() for c in configs}
    groups: dict[tuple[int, str], list[RobotRound]] = {}
    for record in rounds:
        groups.setdefault((record.configuration, record.law), []).append(record)
    for (index, key), group in groups.items():
        vectors: list[Sequence[float] | None] = [None] * s.robots
        for record in group:
            vectors[record.robot] = record.probabilities
        for record in group:
            record.core_difference = check_against_core(record, vectors, yaws[index], laws[key])
    timings["total_s"] = time.perf_counter() - t0
    return SimulationResult(
        settings=s,
        configurations=configs,
        rounds=rounds,
        metrics=metrics,
        timings=timings,
        errors=runner.errors if runner else [],
        failures=runner.failures if runner else {},
    )
