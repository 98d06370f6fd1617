"""Every workload's swarm on Kubernetes, as :class:`KubernetesDeployment` renders it for a run
(``swarmrec/deployments/k8s_workloads.py``): the dvpr, slam and landmarks specs on the local
overlay, each object valid against Kubernetes v1.34.4's own OpenAPI schemas (the validator of
tests/unit/test_k8s_manifests.py), one StatefulSet per kind of the spec with the swarm's robots,
each pod's environment loading with the services' own settings loader and naming files the pod
has (the image's shipped models, the run's input ConfigMap, the detectors' frames on the node),
data volumes exactly for the kinds that keep data, each kind's own Secret, and Prometheus
looking for exactly the spec's kinds. tests/e2e/test_k8s_methods.py runs them on the cluster.
"""

from __future__ import annotations

import base64
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.k8s_workloads import (
    FRAMES_MOUNT,
    IMAGE_MODELS,
    INPUT_MOUNT,
    pod_inputs,
    prometheus_config,
    workload_objects,
)
from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, cluster_spec, secret_name, write_overlay
from swarmrec.errors import ConfigError
from swarmrec.experiments.landmarks.simulation import LandmarkSettings
from swarmrec.experiments.landmarks.simulation import swarm_spec as landmarks_spec
from swarmrec.models import DESCRIPTOR_CENTRES, DETECTOR_MODEL, shipped_model
from swarmrec.runtime.settings import BusSettings
from swarmrec.services import registry
from swarmrec.services.settings import (
    DetectorSettings,
    PlaceSettings,
    RgbdSettings,
    SlamServiceSettings,
    VprSettings,
)
from tests.unit.test_k8s_manifests import (
    _as_mounted,
    ensure_kubectl,
    find,
    kubectl_run,
    robot_environment,
    service_config,
    validate,
    yaml_to_objects,
)

Obj = dict[str, Any]
ROBOTS = 3
NAMESPACE = "run-ns"
NODE_ROOT = Path("/var/lib/swarmrec-k8s/volumes")


def _dvpr(tmp: Path) -> SwarmSpec:
    frames = tmp / "rgbd"
    frames.mkdir()
    table = tmp / "assignment.json"
    table.write_text('{"format": "swarmrec.vpr.assignment/1"}')
    labels = tmp / "labels.txt"
    labels.write_text("person\nchair\n")
    parts = (
        PlaceSettings(n_labels=2),
        DetectorSettings(detector_mode="rgbd", dataset=str(frames), labels_file=labels),
        RgbdSettings(detector_model=str(shipped_model(DETECTOR_MODEL))),
        VprSettings(
            place_method="dvpr", vpr_centres=str(shipped_model(DESCRIPTOR_CENTRES)), vpr_assignment=table
        ),
    )
    return SwarmSpec(
        BusSettings(swarm="lab", n_robots=ROBOTS), registry.WORKLOADS["dvpr"], parts, workload="dvpr"
    )


def _slam(tmp: Path) -> SwarmSpec:
    folder = tmp / "input"
    folder.mkdir()
    for r in range(ROBOTS):
        (folder / f"{r}.g2o").write_text(f"VERTEX_SE2 {r} 0 0 0\n")
    parts = (SlamServiceSettings(slam_folder=folder),)
    return SwarmSpec(
        BusSettings(swarm="lab", n_robots=ROBOTS), registry.WORKLOADS["slam"], parts, workload="slam"
    )


def _landmarks(tmp: Path) -> SwarmSpec:
    return landmarks_spec(LandmarkSettings(out=tmp / "unused", robots=ROBOTS, swarm="lab"))


SPECS = {"dvpr": _dvpr, "slam": _slam, "landmarks": _landmarks}


def _objects(spec: SwarmSpec, tmp: Path) -> tuple[Obj, ...]:
    """What the deployment applies for ``spec`` on the local overlay."""
    ensure_kubectl()
    spec = cluster_spec(spec, ROBOTS)
    folder = write_overlay(spec, NAMESPACE, DEFAULT_OVERLAY, tmp / "overlay")
    rendered = yaml_to_objects(kubectl_run("kustomize", str(folder)))
    inputs = pod_inputs(spec)
    frames = NODE_ROOT / NAMESPACE / "frames" if inputs.frames is not None else None
    return tuple(workload_objects(rendered, inputs, NAMESPACE, frames))


def _pod(objs: tuple[Obj, ...], kind: str) -> Obj:
    return find(objs, "StatefulSet", kind)["spec"]["template"]["spec"]  # type: ignore[no-any-return]


def _files_in_pod(objs: tuple[Obj, ...], kind: str) -> set[Path]:
    """Every file a ``kind`` pod has from the input ConfigMap, by its path in the pod."""
    pod = _pod(objs, kind)
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    (container,) = [c for c in pod["containers"] if c["name"] == "service"]
    out = set()
    for m in container.get("volumeMounts", []):
        cm = volumes[m["name"]].get("configMap")
        if cm is not None and cm["name"] == "input":
            data = find(objs, "ConfigMap", "input")["binaryData"]
            for item in cm["items"]:
                assert item["key"] in data
                out.add(Path(m["mountPath"]) / item["path"])
    return out


@pytest.mark.parametrize("workload", sorted(SPECS))
def test_each_workloads_objects_are_valid_and_run_its_kinds_on_every_robot(
    workload: str, tmp_path: Path
) -> None:
    spec = SPECS[workload](tmp_path)
    objs = _objects(spec, tmp_path)
    assert [e for o in objs for e in validate(o)] == []
    kinds = registry.WORKLOADS[workload]
    statefulsets = {o["metadata"]["name"]: o for o in objs if o["kind"] == "StatefulSet"}
    assert sorted(statefulsets) == sorted(kinds)
    assert {k: s["spec"]["replicas"] for k, s in statefulsets.items()} == dict.fromkeys(kinds, ROBOTS)
    for kind in ("Service", "PodDisruptionBudget"):
        robot_objects = {o["metadata"]["name"] for o in objs if o["kind"] == kind} - {
            "router",
            "gateway",
            "prometheus",
        }
        assert robot_objects == set(kinds)
    for kind in kinds:
        pod = _pod(objs, kind)
        # The pod's own kind: what it serves, the Secret its identity comes from.
        assert [c["args"] for c in pod["containers"]] == [[kind]]
        secrets = {v["secret"]["secretName"] for v in pod["volumes"] if "secret" in v}
        assert secrets == {secret_name(kind)}
        for robot in range(ROBOTS):
            config = service_config(kind, robot_environment(objs, kind, robot))
            assert (config.bus.robot, config.bus.n_robots, config.bus.swarm) == (robot, ROBOTS, "lab")


@pytest.mark.parametrize("workload", sorted(SPECS))
def test_a_data_volume_goes_exactly_to_the_kinds_that_keep_data(workload: str, tmp_path: Path) -> None:
    spec = SPECS[workload](tmp_path)
    objs = _objects(spec, tmp_path)
    rgbd = workload == "dvpr"
    for kind in registry.WORKLOADS[workload]:
        keeps = registry.spec(kind).stateful or (kind == "detector" and rgbd)
        pod = _pod(objs, kind)
        volumes = {v["name"]: v for v in pod["volumes"]}
        assert ("data" in volumes) == keeps, kind
        env = robot_environment(objs, kind, 1)
        assert ("SWARMREC_DATA_DIR" in env) == keeps, kind
        if keeps:  # the local overlay's node folder per pod
            assert volumes["data"]["hostPath"]["path"] == str(NODE_ROOT)


def test_the_dvpr_pods_open_the_shipped_models_in_the_image_and_the_runs_files_from_its_configmap(
    tmp_path: Path,
) -> None:
    spec = _dvpr(tmp_path)
    objs = _objects(spec, tmp_path)
    detector = service_config("detector", robot_environment(objs, "detector", 2))
    owner = service_config("place-owner", robot_environment(objs, "place-owner", 2))
    assert detector.get(RgbdSettings).detector_model == str(IMAGE_MODELS / DETECTOR_MODEL)
    # The image holds the ONNX models only: the shipped centres travel with the run's files.
    assert owner.get(VprSettings).vpr_centres == str(INPUT_MOUNT / "vpr_centres.npz")
    assert owner.get(VprSettings).vpr_assignment == INPUT_MOUNT / "vpr_assignment.json"
    assert {INPUT_MOUNT / "vpr_assignment.json", INPUT_MOUNT / "vpr_centres.npz"} <= _files_in_pod(
        objs, "place-owner"
    )
    centres = find(objs, "ConfigMap", "input")["binaryData"]["vpr_centres.npz"]
    assert base64.b64decode(centres) == shipped_model(DESCRIPTOR_CENTRES).read_bytes()
    # The detector reads its frames from the node folder and its labels from the ConfigMap.
    settings = detector.get(DetectorSettings)
    assert settings.dataset == str(FRAMES_MOUNT) and settings.labels_file == INPUT_MOUNT / "labels_file.txt"
    assert INPUT_MOUNT / "labels_file.txt" in _files_in_pod(objs, "detector")
    frames = next(v for v in _pod(objs, "detector")["volumes"] if v["name"] == "frames")
    assert frames["hostPath"] == {"path": str(NODE_ROOT / NAMESPACE / "frames"), "type": "Directory"}
    # The ConfigMap holds the files themselves.
    data = find(objs, "ConfigMap", "input")["binaryData"]
    assert base64.b64decode(data["labels_file.txt"]) == b"person\nchair\n"
    # The gateway reads the same full-image settings, so it sees the same files.
    gateway = find(objs, "Deployment", "gateway")["spec"]["template"]["spec"]
    assert "input" in {v["name"] for v in gateway["volumes"]}


def test_each_slam_pod_finds_the_teams_robot_folder_in_its_configmap(tmp_path: Path) -> None:
    objs = _objects(_slam(tmp_path), tmp_path)
    config = service_config("slam", robot_environment(objs, "slam", 0))
    folder = config.get(SlamServiceSettings).slam_folder
    assert folder == INPUT_MOUNT / "slam_folder"
    assert _files_in_pod(objs, "slam") == {folder / f"{r}.g2o" for r in range(ROBOTS)}


@pytest.mark.parametrize("workload", sorted(SPECS))
def test_prometheus_looks_for_the_router_the_gateway_and_exactly_the_specs_kinds(
    workload: str, tmp_path: Path
) -> None:
    objs = _objects(SPECS[workload](tmp_path), tmp_path)
    (cm,) = [o for o in objs if o["kind"] == "ConfigMap" and "prometheus.yml" in o.get("data", {})]
    names = [
        line.strip()[2:] for line in cm["data"]["prometheus.yml"].splitlines() if "- _metrics._tcp." in line
    ]
    assert names == [f"_metrics._tcp.{k}" for k in ("router", "gateway", *registry.WORKLOADS[workload])]


def test_the_prometheus_names_are_rewritten_wherever_the_list_ends() -> None:
    text = "names:\n  - _metrics._tcp.router\n  - _metrics._tcp.detector\n"
    assert prometheus_config(text, ("slam",)) == "names:\n  - _metrics._tcp.router\n  - _metrics._tcp.slam\n"


def test_the_places_swarm_is_left_as_the_manifests_spell_it(tmp_path: Path) -> None:
    from swarmrec.evaluation.source import DatasetSource
    from swarmrec.experiments.places.pipeline import prepare
    from swarmrec.experiments.places.settings import PlacesSettings

    run = PlacesSettings(source=DatasetSource(frames=30), robots=2, swarm="lab", out=tmp_path)
    spec = prepare(run, dataset_dir=tmp_path / "dataset").spec
    folder = write_overlay(spec, NAMESPACE, DEFAULT_OVERLAY, tmp_path / "overlay")
    ensure_kubectl()
    rendered = yaml_to_objects(kubectl_run("kustomize", str(folder)))
    assert pod_inputs(spec).spec == spec
    assert workload_objects(rendered, pod_inputs(spec), NAMESPACE, None) == rendered


def test_files_too_large_for_a_configmap_are_refused(tmp_path: Path) -> None:
    spec = _slam(tmp_path)
    (tmp_path / "input" / "3.g2o").write_bytes(json.dumps(["x" * 1000] * 1100).encode())
    with pytest.raises(ConfigError, match="holds 1 MiB"):
        pod_inputs(spec)


def test_the_machines_openblas_settings_reach_every_robots_pod(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    spec = _slam(tmp_path)
    objs = _objects(spec, tmp_path)
    for kind in spec.kinds:
        for robot in range(ROBOTS):
            assert robot_environment(objs, kind, robot)["OPENBLAS_CORETYPE"] == "Haswell", (kind, robot)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from swarmrec.deployments.kubernetes import kubernetes_pki

    return kubernetes_pki(tmp_path_factory.mktemp("k8s-pki") / "pki", "lab", ROBOTS, NAMESPACE)


def _identity(pki: Path, kind: str, tmp: Path, monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """What robot 1's ``kind`` pod's init container copies out of its kind's Secret."""
    from swarmrec.cli import main
    from swarmrec.deployments.kubernetes import secret_objects

    objs = secret_objects(pki, "lab", ROBOTS, NAMESPACE, registry.WORKLOADS["landmarks"])
    secrets = {o["metadata"]["name"]: o for o in objs}
    mounted = _as_mounted(secrets[secret_name(kind)], tmp / "secrets")
    for name, value in {"SWARMREC_ROBOT": "1", "SWARMREC_SWARM": "lab", "SWARMREC_N_ROBOTS": "3"}.items():
        monkeypatch.setenv(name, value)
    assert main(["k8s", "identity", "--kind", kind, "--from", str(mounted), "--to", str(tmp / "pki")]) == 0
    return sorted(p.name for p in (tmp / "pki").iterdir())


def test_a_pod_that_checks_its_peers_signatures_gets_their_public_certificates_as_the_registry_says(
    pki: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fusion = ["ca.pem", "r1.fusion.lab.key", "r1.fusion.lab.pem"]
    detector = ["ca.pem", "r1.detector.lab.key", "r1.detector.lab.pem"]
    peers = ["r0.fusion.lab.pem", "r2.fusion.lab.pem"]  # never their keys
    assert _identity(pki, "fusion", tmp_path / "a", monkeypatch) == sorted([*fusion, *peers])
    assert _identity(pki, "detector", tmp_path / "b", monkeypatch) == detector
    # The field decides, not the kind's name.
    for kind, value in (("fusion", False), ("detector", True)):
        monkeypatch.setitem(registry.REGISTRY, kind, replace(registry.spec(kind), peer_certificates=value))
    assert _identity(pki, "fusion", tmp_path / "c", monkeypatch) == fusion
    peers = ["r0.detector.lab.pem", "r2.detector.lab.pem"]
    assert _identity(pki, "detector", tmp_path / "d", monkeypatch) == sorted([*detector, *peers])
