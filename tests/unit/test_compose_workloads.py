"""The compose files of the dvpr and slam workloads: what each container mounts and sees.

The host paths the settings name (an rgbd detector's model, the centres, an assignment, a
SLAM robot folder) become read-only mounts of copies beside the compose file, and the
containers' settings name those mounts; an rgbd detector's data folder is a bind mount the
run reads back; the swarm file the run checks against records the settings as the
containers see them, whatever the host paths.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.compose import (
    ComposeDeployment,
    ComposeSettings,
    compose_document,
    write_compose,
)
from swarmrec.errors import ConfigError
from swarmrec.experiments.landmarks.simulation import LandmarkSettings
from swarmrec.experiments.landmarks.simulation import swarm_spec as landmarks_spec
from swarmrec.experiments.slam.keep import from_record as slam_from_record
from swarmrec.experiments.vpr.keep import from_record as vpr_from_record
from swarmrec.runtime.settings import BusSettings
from swarmrec.services import registry
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import (
    DetectorSettings,
    PlaceSettings,
    RgbdSettings,
    SlamServiceSettings,
    VprSettings,
)


def dvpr_spec(tmp: Path, robots: int = 2) -> SwarmSpec:
    (tmp / "frames").mkdir(parents=True, exist_ok=True)
    for name in ("detector.onnx", "centres.npz", "table.json"):
        (tmp / name).write_bytes(name.encode())
    return SwarmSpec(
        BusSettings(swarm="compose", n_robots=robots),
        WORKLOADS["dvpr"],
        (
            PlaceSettings(lockstep=True),
            DetectorSettings(detector_mode="rgbd", dataset=str(tmp / "frames")),
            RgbdSettings(detector_model=str(tmp / "detector.onnx")),
            VprSettings(
                place_method="dvpr", vpr_centres=str(tmp / "centres.npz"), vpr_assignment=tmp / "table.json"
            ),
        ),
        workload="dvpr",
    )


def test_a_dvpr_swarms_host_files_are_copied_and_mounted_into_the_kinds_that_read_them(
    tmp_path: Path,
) -> None:
    spec = dvpr_spec(tmp_path / "host")
    out = tmp_path / "compose"
    info = write_compose(spec, ComposeSettings(out=out, security="insecure"))
    assert sorted(p.name for p in (out / "files").iterdir()) == [
        "detector_model.onnx",
        "vpr_assignment.json",
        "vpr_centres.npz",
    ]
    assert (out / "files" / "vpr_centres.npz").read_bytes() == b"centres.npz"
    doc = compose_document(spec, ComposeSettings(out=out, security="insecure"))
    services = doc["services"]
    for r in range(2):
        detector = services[f"r{r}-detector"]
        assert "./files:/data/files:ro" in detector["volumes"]
        assert f"./data/robot{r}/detector:/var/lib/swarmrec" in detector["volumes"]
        assert detector["environment"]["SWARMREC_DETECTOR_MODEL"] == "/data/files/detector_model.onnx"
        assert detector["environment"]["SWARMREC_DATA_DIR"] == "/var/lib/swarmrec"
        owner = services[f"r{r}-place-owner"]
        assert "./files:/data/files:ro" in owner["volumes"]
        assert owner["environment"]["SWARMREC_VPR_CENTRES"] == "/data/files/vpr_centres.npz"
        assert owner["environment"]["SWARMREC_VPR_ASSIGNMENT"] == "/data/files/vpr_assignment.json"
        # The verifier reads none of them: it mounts nothing of the host's.
        assert services[f"r{r}-verifier"]["volumes"] == [f"r{r}-verifier-data:/var/lib/swarmrec"]
    assert services["gateway"]["volumes"] == ["./files:/data/files:ro"]
    # The run checks the swarm against settings as the containers see them: no host path.
    assert str(tmp_path) not in json.dumps(info.shared_env)
    assert info.shared_env["SWARMREC_VPR_CENTRES"] == "/data/files/vpr_centres.npz"
    # The detectors' data folders are on this host, empty, where the run reads them back.
    assert info.detections_dir == str((out / "data").resolve())
    assert ComposeDeployment(out).local_data_dir == (out / "data").resolve()
    assert sorted(p.name for p in (out / "data").iterdir()) == ["robot0", "robot1"]
    assert list((out / "data" / "robot0" / "detector").iterdir()) == []


def test_a_places_swarm_has_no_detections_on_the_host(tmp_path: Path) -> None:
    (tmp_path / "constellations").mkdir()
    spec = SwarmSpec(
        BusSettings(swarm="compose", n_robots=2),
        WORKLOADS["places"],
        (DetectorSettings(dataset=str(tmp_path / "constellations")),),
        workload="places",
    )
    write_compose(spec, ComposeSettings(out=tmp_path / "compose", security="insecure"))
    assert ComposeDeployment(tmp_path / "compose").local_data_dir is None
    assert not (tmp_path / "compose" / "files").exists()


def test_a_slam_teams_folder_is_copied_and_mounted_read_only_into_each_slam_service(tmp_path: Path) -> None:
    folder = tmp_path / "graphs"
    folder.mkdir()
    for r in range(3):
        (folder / f"{r}.g2o").write_text(f"robot {r}\n")
    spec = SwarmSpec(
        BusSettings(swarm="team", n_robots=3),
        WORKLOADS["slam"],
        (SlamServiceSettings(slam_folder=folder),),
        workload="slam",
    )
    out = tmp_path / "compose"
    info = write_compose(spec, ComposeSettings(out=out, security="insecure"))
    assert sorted(p.name for p in (out / "slam").iterdir()) == ["0.g2o", "1.g2o", "2.g2o"]
    services = compose_document(spec, ComposeSettings(out=out, security="insecure"))["services"]
    for r in range(3):
        slam = services[f"r{r}-slam"]
        assert slam["volumes"] == ["./slam:/data/slam:ro"]
        assert slam["environment"]["SWARMREC_SLAM_FOLDER"] == "/data/slam"
    assert "volumes" not in services["gateway"]
    assert info.shared_env["SWARMREC_SLAM_FOLDER"] == "/data/slam"


def test_the_hosts_openblas_settings_reach_every_container_but_not_the_swarms_settings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    spec = dvpr_spec(tmp_path / "host")
    doc = compose_document(spec, ComposeSettings(out=tmp_path / "compose", security="insecure"))
    for name, service in doc["services"].items():
        if name != "prometheus":
            assert service["environment"]["OPENBLAS_CORETYPE"] == "Haswell", name
    info = write_compose(spec, ComposeSettings(out=tmp_path / "compose", security="insecure"))
    assert "OPENBLAS_CORETYPE" not in info.shared_env


def test_a_record_of_another_experiment_is_not_read_as_a_dvpr_run_or_a_slam_team() -> None:
    places = {"dataset": "synthetic", "robots": 2, "preset": "paper", "swarm": "s", "request_timeout_s": 5.0}
    with pytest.raises(ConfigError, match="not a full-image run"):
        vpr_from_record(places)
    with pytest.raises(ConfigError, match="not a SLAM team"):
        slam_from_record(places)


def test_a_solve_through_a_running_team_cannot_change_what_the_team_runs(tmp_path: Path) -> None:
    record = {
        "format": "swarmrec.slam-record/1",
        "folder": None,
        "world": "chairs",
        "robots": 3,
        "seed": 0,
        "swarm": "team",
        "request_timeout_s": 5.0,
        "peer_timeout_s": 10.0,
    }
    settings = slam_from_record(record, out=tmp_path / "run", progress=False)
    assert (settings.robots, settings.swarm, settings.folder) == (3, "team", None)
    with pytest.raises(ConfigError, match="fixes robots"):
        slam_from_record(record, out=tmp_path / "run", robots=4)


def _secret_files(out: Path, service: str) -> list[str]:
    return sorted(p.name for p in (out / "secrets" / service).iterdir())


def _peer_certificates(monkeypatch: pytest.MonkeyPatch, kind: str, value: bool) -> None:
    monkeypatch.setitem(registry.REGISTRY, kind, replace(registry.spec(kind), peer_certificates=value))


def test_a_kind_that_checks_its_peers_signatures_gets_their_public_certificates_as_the_registry_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spec = landmarks_spec(LandmarkSettings(out=tmp_path / "unused", robots=3, swarm="lab"))
    write_compose(spec, ComposeSettings(out=tmp_path / "a"))
    # The fusion entry says so: robot 1's fusion container has the other robots' certificates,
    # never their keys; its detector (which checks no peer) has its own pair only.
    fusion = ["ca.pem", "r1.fusion.lab.key", "r1.fusion.lab.pem"]
    detector = ["ca.pem", "r1.detector.lab.key", "r1.detector.lab.pem"]
    peers = ["r0.fusion.lab.pem", "r2.fusion.lab.pem"]
    assert _secret_files(tmp_path / "a", "r1-fusion") == sorted([*fusion, *peers])
    assert _secret_files(tmp_path / "a", "r1-detector") == detector
    # The field decides, not the kind's name.
    _peer_certificates(monkeypatch, "fusion", False)
    _peer_certificates(monkeypatch, "detector", True)
    write_compose(spec, ComposeSettings(out=tmp_path / "b"))
    assert _secret_files(tmp_path / "b", "r1-fusion") == fusion
    peers = ["r0.detector.lab.pem", "r2.detector.lab.pem"]
    assert _secret_files(tmp_path / "b", "r1-detector") == sorted([*detector, *peers])
