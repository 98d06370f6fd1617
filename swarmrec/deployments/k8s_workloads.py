"""Every workload of the registry on Kubernetes: the robot StatefulSets of a spec's kinds.

The manifests (``k8s/``) spell out the places workload: a StatefulSet per kind
(index-shard, verifier, descriptor, detector), each patched by the overlay (robot id from
the ordinal, the identity init container, probes, resources, and for a stateful kind its
data volume: a claim per pod, or the local overlay's node folder). Any other spec (the
``dvpr``, ``slam`` and ``landmarks`` workloads, a plug-in's kind, detectors that read
RGB-D frames) is made here from the rendered overlay, so it carries whatever the overlay
says a robot pod is:

* a kind the overlay has keeps its objects; the overlay's kinds the spec lacks go; a kind
  it lacks (and the detector, unless it replays constellations) gets the StatefulSet,
  headless Service and PodDisruptionBudget of the overlay's verifier
  (:data:`TEMPLATE_KIND`, the plainest stateful robot kind) under its own name, serving
  ``swarmrec serve <kind>`` with its own Secret; a kind the registry does not call
  stateful, and that keeps nothing on disk, loses the data volume;
* the host files the spec's settings name (an assignment table, the k-means centres, a
  SLAM team's robot folder, the label list) travel in one ConfigMap, ``input``, mounted
  read-only at :data:`INPUT_MOUNT` into the pods whose kind reads them; the shipped ONNX
  models are the image's own (:data:`IMAGE_MODELS`), not copied;
* detectors that read RGB-D frames get them from a node folder (:data:`FRAMES_MOUNT`;
  frames are megabytes, a ConfigMap holds one): only an overlay that keeps volumes on
  the node (``k8s/overlays/local``) can run them, and they keep what they detect in their
  data volume, which the deployment copies back as a local run lays it out
  (``robot<r>/detector``);
* Prometheus scrapes the SRV records of the spec's kinds.

The identities are the kinds' (:func:`robot_kinds_of` names the Secrets to make); the
router's access control covers every registered kind already.
"""

from __future__ import annotations

import base64
import copy
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from swarmrec.deployments.base import SwarmSpec
from swarmrec.errors import ConfigError
from swarmrec.models import model_search_path
from swarmrec.runtime.settings import Component
from swarmrec.services import registry
from swarmrec.services.settings import (
    ClassifierSettings,
    DetectorSettings,
    RgbdSettings,
    SlamServiceSettings,
    VprSettings,
)

__all__ = [
    "FRAMES_MOUNT",
    "IMAGE_MODELS",
    "INPUT_CONFIGMAP",
    "INPUT_MOUNT",
    "PLACES_KINDS",
    "TEMPLATE_KIND",
    "PodInputs",
    "detections_of",
    "made_here",
    "pod_inputs",
    "prometheus_config",
    "robot_kinds_of",
    "workload_objects",
]

Obj = dict[str, Any]

#: The robot kinds the manifests spell out, one StatefulSet each.
PLACES_KINDS: tuple[str, ...] = registry.WORKLOADS["places"]
#: The rendered StatefulSet every other kind's is made from.
TEMPLATE_KIND = "verifier"
#: Where the image keeps the shipped models (deploy/Dockerfile: SWARMREC_MODELS).
IMAGE_MODELS = Path("/opt/swarmrec/models")
INPUT_CONFIGMAP = "input"
INPUT_MOUNT = Path("/data/input")
FRAMES_MOUNT = Path("/data/frames")
#: The decoded bytes a ConfigMap holds at most (the apiserver's limit), less room for its keys.
INPUT_LIMIT = (1 << 20) - 4096
ROBOT_LABEL = "swarmrec.io/robot-service"
STATEFUL_LABEL = "swarmrec.io/stateful"
COMPONENT = "app.kubernetes.io/component"
#: The settings that name a host file (or, for the SLAM team, a folder) a service opens.
FILE_SETTINGS: tuple[tuple[type[Component], str], ...] = (
    (DetectorSettings, "labels_file"),
    (RgbdSettings, "detector_model"),
    (VprSettings, "descriptor_model"),
    (VprSettings, "vpr_centres"),
    (VprSettings, "vpr_assignment"),
    (ClassifierSettings, "classifier_model"),
    (SlamServiceSettings, "slam_folder"),
)


@dataclass(frozen=True)
class PodInputs:
    """A spec as its pods see it, and what must reach them for that."""

    #: The spec with every host path replaced by the path in the pod.
    spec: SwarmSpec
    #: The ``input`` ConfigMap's files: path under :data:`INPUT_MOUNT` -> the host file.
    files: dict[str, Path] = field(default_factory=dict)
    #: The RGB-D frames folder the detectors read (at :data:`FRAMES_MOUNT`); None: none.
    frames: Path | None = None


def _rgbd(spec: SwarmSpec) -> bool:
    detector = spec.component(DetectorSettings)
    return (
        "detector" in spec.kinds
        and isinstance(detector, DetectorSettings)
        and detector.detector_mode == "rgbd"
    )


def made_here(spec: SwarmSpec) -> bool:
    """Whether the spec's robot StatefulSets are made here rather than taken as rendered: any
    spec but the manifests' own places swarm of replaying detectors."""
    detector = spec.component(DetectorSettings)
    replaying = not isinstance(detector, DetectorSettings) or detector.detector_mode == "replay"
    return spec.kinds != PLACES_KINDS or not replaying


def _shipped(path: Path) -> Path | None:
    """Where the image has ``path``, when it is one of the shipped ONNX models; else None. (The
    image holds the models only, deploy/build.sh: the shipped k-means centres travel as any file.)"""
    resolved = path.resolve()
    if resolved.suffix != ".onnx":
        return None
    for folder in model_search_path():
        if resolved.is_relative_to(folder.resolve()):
            return IMAGE_MODELS / resolved.relative_to(folder.resolve())
    return None


def _in_pod(name: str, host: Path, files: dict[str, Path]) -> Path:
    """The path a pod opens ``host`` at (adding it to ``files`` unless it is a shipped model)."""
    shipped = _shipped(host)
    if shipped is not None:
        return shipped
    if host.is_dir():
        for path in sorted(host.iterdir()):
            if path.is_file():
                files[f"{name}/{path.name}"] = path
        return INPUT_MOUNT / name
    if not host.is_file():
        raise ConfigError(f"{host} ({name}, a file the swarm's settings name) is not a file")
    files[f"{name}{host.suffix}"] = host
    return INPUT_MOUNT / f"{name}{host.suffix}"


def pod_inputs(spec: SwarmSpec) -> PodInputs:
    """``spec`` with the host paths its settings name replaced by the pods' (see the module
    docstring); a detector that replays constellations keeps its dataset, which the run's
    overlay ships as the places swarm's (:func:`swarmrec.deployments.kubernetes.write_overlay`)."""
    if not made_here(spec):
        return PodInputs(spec)
    files: dict[str, Path] = {}
    changed: dict[type[Component], Component] = {}
    for comp, name in FILE_SETTINGS:
        given = changed.get(comp) or spec.component(comp)
        value = getattr(given, name) if given is not None else None
        if given is None or not value:
            continue
        inside = _in_pod(name, Path(value), files)
        changed[comp] = given.with_(**{name: inside if isinstance(value, Path) else str(inside)})
    frames = None
    detector = changed.get(DetectorSettings) or spec.component(DetectorSettings)
    if _rgbd(spec) and isinstance(detector, DetectorSettings):
        frames = Path(detector.dataset).resolve()
        if not frames.is_dir():
            raise ConfigError(f"{frames}: the RGB-D frames the detectors read are not a folder")
        changed[DetectorSettings] = detector.with_(dataset=str(FRAMES_MOUNT))
    size = sum(p.stat().st_size for p in files.values())
    if size > INPUT_LIMIT:
        raise ConfigError(
            f"the files the swarm's settings name take {size / 1e6:.2f} MB; they travel in a ConfigMap, "
            f"which holds 1 MiB: {', '.join(str(p) for p in files.values())}"
        )
    parts = tuple(changed.get(type(c), c) for c in spec.components)
    return PodInputs(
        SwarmSpec(spec.bus, spec.kinds, parts, spec.workload, dict(spec.overrides), spec.swarm_kinds),
        files,
        frames,
    )


# --- the objects ----------------------------------------------------------------------------


def _component(obj: Obj) -> str:
    return str(obj["metadata"].get("labels", {}).get(COMPONENT, ""))


def robot_kinds_of(objects: Sequence[Obj]) -> list[str]:
    """The robot kinds a rendered swarm runs (its robot StatefulSets), in order."""
    return [
        _component(o)
        for o in objects
        if o["kind"] == "StatefulSet" and o["metadata"].get("labels", {}).get(ROBOT_LABEL) == "true"
    ]


def _renamed(value: Any, old: str, new: str) -> Any:
    """``value`` with every string that names kind ``old`` (its name, its Secret) naming ``new``."""
    if isinstance(value, dict):
        return {k: _renamed(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [_renamed(v, old, new) for v in value]
    if value == old:
        return new
    if value == f"swarmrec-tls-{old}":
        return f"swarmrec-tls-{new}"
    return value


def _without_data(sts: Obj) -> None:
    """Drop a StatefulSet's data volume (claims, node folder, its chown container, the setting)."""
    sts["spec"].pop("volumeClaimTemplates", None)
    sts["spec"].pop("persistentVolumeClaimRetentionPolicy", None)
    sts["metadata"].get("labels", {}).pop(STATEFUL_LABEL, None)
    pod = sts["spec"]["template"]["spec"]
    pod["volumes"] = [v for v in pod.get("volumes", []) if v["name"] != "data"]
    pod["initContainers"] = [
        c
        for c in pod.get("initContainers", [])
        if all(m["name"] != "data" for m in c.get("volumeMounts", []))
    ]
    for c in pod.get("containers", []):
        c["volumeMounts"] = [m for m in c.get("volumeMounts", []) if m["name"] != "data"]
        c["env"] = [e for e in c.get("env", []) if e["name"] != "SWARMREC_DATA_DIR"]


def _service_container(pod: Obj) -> Obj:
    for c in pod.get("containers", []):
        if c["name"] in ("service", "gateway"):
            return c  # type: ignore[no-any-return]
    raise ConfigError("a swarm pod of the overlay has no service container")


def _mount(pod: Obj, volume: Obj, path: Path) -> None:
    """Mount ``volume`` read-only at ``path`` in the pod's service container."""
    pod.setdefault("volumes", []).append(volume)
    _service_container(pod).setdefault("volumeMounts", []).append(
        {"name": volume["name"], "mountPath": str(path), "readOnly": True}
    )


def _reads_input(kind: str, inputs: PodInputs) -> bool:
    """Whether ``kind`` reads a setting that names one of the input files."""
    comps = {comp for comp, _ in FILE_SETTINGS}
    return bool(inputs.files) and any(c in comps for c in registry.spec(kind).all_components)


def _input_volume(inputs: PodInputs) -> Obj:
    items = [{"key": _key(path), "path": path} for path in sorted(inputs.files)]
    return {"name": "input", "configMap": {"name": INPUT_CONFIGMAP, "items": items}}


def _key(path: str) -> str:
    """A ConfigMap key for a file's path under the mount (keys hold no slash)."""
    return path.replace("/", ".")


def _robot_objects(
    template: list[Obj], kind: str, spec: SwarmSpec, inputs: PodInputs, frames_on_node: Path | None
) -> list[Obj]:
    """``kind``'s StatefulSet, headless Service and PodDisruptionBudget, from the template's."""
    made = [_renamed(copy.deepcopy(o), TEMPLATE_KIND, kind) for o in template]
    sts = next(o for o in made if o["kind"] == "StatefulSet")
    sts["spec"]["replicas"] = spec.robots
    keeps_data = registry.spec(kind).stateful or (kind == "detector" and inputs.frames is not None)
    if not keeps_data:
        _without_data(sts)
    pod = sts["spec"]["template"]["spec"]
    if _reads_input(kind, inputs):
        _mount(pod, _input_volume(inputs), INPUT_MOUNT)
    if kind == "detector":
        detector = inputs.spec.component(DetectorSettings)
        env = _service_container(pod).setdefault("env", [])
        if isinstance(detector, DetectorSettings) and detector.dataset:
            env.append({"name": "SWARMREC_DATASET", "value": detector.dataset})
        if isinstance(detector, DetectorSettings) and detector.labels_file is not None:
            env.append({"name": "SWARMREC_LABELS_FILE", "value": str(detector.labels_file)})
        if frames_on_node is not None:
            volume = {"name": "frames", "hostPath": {"path": str(frames_on_node), "type": "Directory"}}
            _mount(pod, volume, FRAMES_MOUNT)
    return made


_SRV = re.compile(r"^(\s*)- _metrics\._tcp\.([a-z0-9-]+)\s*$")


def prometheus_config(text: str, kinds: Sequence[str]) -> str:
    """``prometheus.yml`` with its SRV names those of the swarm kinds it lists and ``kinds``."""
    lines, out, indent = text.splitlines(), [], None
    swarm = set(registry.kinds("swarm"))
    for line in lines:
        m = _SRV.match(line)
        if m is None:
            if indent is not None:
                out.extend(f"{indent}- _metrics._tcp.{k}" for k in kinds)
                indent = None
            out.append(line)
        elif m.group(2) in swarm:
            out.append(line)
        else:
            indent = m.group(1)
    if indent is not None:
        out.extend(f"{indent}- _metrics._tcp.{k}" for k in kinds)
    return "\n".join(out) + "\n"


def _input_configmap(namespace: str, inputs: PodInputs) -> Obj:
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": INPUT_CONFIGMAP,
            "namespace": namespace,
            "labels": {"app.kubernetes.io/name": "swarmrec", "app.kubernetes.io/part-of": "swarmrec"},
        },
        "binaryData": {
            _key(path): base64.b64encode(host.read_bytes()).decode()
            for path, host in sorted(inputs.files.items())
        },
    }


def workload_objects(
    objects: Sequence[Obj], inputs: PodInputs, namespace: str, frames_on_node: Path | None
) -> list[Obj]:
    """The rendered overlay's objects running ``inputs.spec``'s kinds (see the module docstring):
    the overlay's own robot objects replaced by the kinds', the input ConfigMap added, the
    gateway given the input it reads, Prometheus told where the kinds' pods are."""
    spec = inputs.spec
    if not made_here(spec):
        return list(objects)
    rendered = set(robot_kinds_of(objects))
    template = [
        o
        for o in objects
        if o["kind"] in ("StatefulSet", "Service", "PodDisruptionBudget") and _component(o) == TEMPLATE_KIND
    ]
    if len(template) != 3:
        raise ConfigError(
            f"the overlay has no {TEMPLATE_KIND} StatefulSet, headless Service and PodDisruptionBudget "
            "to make the workload's robot services from"
        )
    # A kind the overlay has keeps its objects (the index shards' own grace period ...), but the
    # detector when it does not replay constellations (nor then make a world to replay).
    kept = (rendered & set(spec.kinds)) - {"detector"}
    out: list[Obj] = []
    for obj in objects:
        robot = (
            obj["kind"] in ("StatefulSet", "Service", "PodDisruptionBudget") and _component(obj) in rendered
        )
        if robot and _component(obj) not in kept:
            continue
        obj = copy.deepcopy(obj)
        if obj["kind"] == "ConfigMap" and "prometheus.yml" in obj.get("data", {}):
            obj["data"]["prometheus.yml"] = prometheus_config(obj["data"]["prometheus.yml"], spec.kinds)
        if (
            obj["kind"] == "Deployment"
            and _component(obj) in spec.swarm_kinds
            and _reads_input(_component(obj), inputs)
        ):
            _mount(obj["spec"]["template"]["spec"], _input_volume(inputs), INPUT_MOUNT)
        if obj["kind"] == "StatefulSet" and robot and _reads_input(_component(obj), inputs):
            _mount(obj["spec"]["template"]["spec"], _input_volume(inputs), INPUT_MOUNT)
        out.append(obj)
    for kind in spec.kinds:
        if kind not in kept:
            out.extend(_robot_objects(template, kind, spec, inputs, frames_on_node))
    if inputs.files:
        out.append(_input_configmap(namespace, inputs))
    return out


def detections_of(
    objects: Sequence[Obj], namespace: str, roots: Sequence[Path], robots: int
) -> dict[int, Path]:
    """The node folders of the detectors' data volumes (``<root>/<namespace>/detector-<r>``), when
    the detectors keep data on this node."""
    for obj in objects:
        if obj["kind"] == "StatefulSet" and obj["metadata"]["name"] == "detector":
            volumes = {v["name"]: v for v in obj["spec"]["template"]["spec"].get("volumes", [])}
            host = volumes.get("data", {}).get("hostPath")
            if host and Path(host["path"]) in roots:
                return {r: Path(host["path"]) / namespace / f"detector-{r}" for r in range(robots)}
    return {}
