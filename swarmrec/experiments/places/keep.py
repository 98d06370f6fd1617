"""A place-recognition run's swarm left running for later runs to attach to.

Each function prepares the run's data and spec (:func:`.pipeline.prepare`) and puts the
swarm where it is kept; a later ``swarmrec run --attach DIR`` replays through it:

    local_up        local processes (``swarmrec up``), started, ready, index settled
    compose         the compose files of the swarm (``swarmrec compose up`` starts them)
    kubernetes_up   a Kubernetes namespace (``swarmrec k8s up``), ready, swarm.json written

The pipeline itself (:func:`.pipeline.main`) takes whatever deployment it is given; this
module is where a run meets the deployments that outlive it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from swarmrec.deployments.compose import ComposeSettings, SwarmFile, write_compose
from swarmrec.deployments.kubernetes import KubernetesDeployment, KubernetesSettings
from swarmrec.deployments.local import LocalDeployment
from swarmrec.errors import ConfigError
from swarmrec.experiments.places.pipeline import SETTLE_TIMEOUT_S, prepare
from swarmrec.experiments.places.settings import PlacesSettings
from swarmrec.services.settings import DetectorSettings

__all__ = ["compose", "kubernetes_up", "local_up"]


def compose(settings: PlacesSettings, compose_settings: ComposeSettings) -> SwarmFile:
    """Write the compose files of this run's swarm (its dataset copied beside them); a later
    ``swarmrec run --attach`` reads the run back from ``swarm.json``."""
    out = compose_settings.out.resolve()
    spec = prepare(settings, dataset_dir=out / "dataset").spec
    return write_compose(spec, compose_settings, experiment=settings.record())


def kubernetes_up(settings: PlacesSettings, k8s: KubernetesSettings) -> KubernetesDeployment:
    """This run's swarm on Kubernetes, left running (``swarmrec k8s up``): deployed, ready, and
    ``<out>/swarm.json`` written, so ``swarmrec run --attach <out>`` replays through it."""
    deployment = KubernetesDeployment(k8s.with_(keep=True))
    spec = prepare(settings, dataset_dir=k8s.out.resolve() / "dataset").spec
    try:
        deployment.start(spec, progress=settings.progress)
        deployment.wait_ready()
    except BaseException:
        if deployment.created:  # never a namespace that was there before
            deployment.remove()
        raise
    deployment.write_attach_file(settings.record())
    return deployment


def local_up(settings: PlacesSettings, deployment: LocalDeployment) -> dict[str, Any]:
    """This run's swarm on ``deployment`` (local processes), left running (``swarmrec up``):
    started, ready, its index settled. Returns the experiment record a later ``swarmrec
    run --attach`` replays: the dataset as the detectors read it (so the attached run's
    spec names the same folder), the rest as given."""
    if settings.pixels.enabled:
        raise ConfigError(
            "a swarm kept up replays constellations; a run from pixels starts its own (swarmrec run)"
        )
    if deployment.emulated_links is not None:
        raise ConfigError("emulated links belong to one run: use swarmrec run --link-...")
    prepared = prepare(settings, dataset_dir=settings.out / "dataset")
    spec = prepared.spec
    try:
        deployment.start(spec, progress=settings.progress)
        deployment.wait_ready()
        with deployment.client(settings.request_timeout_s) as client:
            shards = spec.bus.n_robots if "index-shard" in spec.kinds else None
            client.wait_index_settled(timeout_s=SETTLE_TIMEOUT_S, shards=shards)
    except BaseException:
        deployment.stop()
        raise
    detector = spec.component(DetectorSettings)
    assert isinstance(detector, DetectorSettings)
    source = settings.source
    groundtruth = source.groundtruth
    original = Path(source.dataset)
    if groundtruth is None and not source.synthetic and (original / "groundtruth.txt").is_file():
        groundtruth = original / "groundtruth.txt"
    return settings.record() | {
        "dataset": str(Path(detector.dataset).resolve()),
        "seed": 0,
        "frames": None,
        "labels": str(detector.labels_file) if detector.labels_file else None,
        "groundtruth": str(groundtruth.resolve()) if groundtruth else None,
    }
