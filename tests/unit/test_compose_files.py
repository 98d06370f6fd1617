"""The generated compose and Prometheus files, and the YAML writer behind them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.compose import (
    ComposeDeployment,
    ComposeSettings,
    compose_document,
    prometheus_document,
    read_swarm_file,
    render_yaml,
    service_name,
    write_compose,
)
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, swarm_spec
from swarmrec.experiments.places.pipeline import prepare
from swarmrec.experiments.places.settings import PlacesSettings
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import DetectorSettings, PlaceSettings

PLACES = ("index-shard", "verifier", "descriptor", "detector")


def places_spec(robots: int, bounds: tuple[int, ...], dataset: Path) -> SwarmSpec:
    return SwarmSpec(
        BusSettings(swarm="compose", n_robots=robots),
        WORKLOADS["places"],
        (PlaceSettings(label_bounds=bounds, lockstep=True), DetectorSettings(dataset=str(dataset))),
        workload="places",
    )


def test_render_yaml_writes_nested_maps_and_lists_in_block_style() -> None:
    doc = {"a": {"b": [1, "x"], "c": {}}, "d": [{"e": True, "f": None}], "g": []}
    assert render_yaml(doc) == ('a:\n  b:\n    - 1\n    - "x"\n  c: {}\nd:\n  - e: true\n    f: null\ng: []')


@pytest.mark.parametrize(
    "text", ["on", "0755", "1.10", "a: b", "#not a comment", "- x", 'say "hi"', "\u00e9"]
)
def test_render_yaml_quotes_every_string_so_none_is_retyped(text: str) -> None:
    # A JSON string literal is a YAML double-quoted scalar with the same value.
    assert render_yaml({"k": text}) == f"k: {json.dumps(text)}"


def test_compose_has_a_router_four_services_per_robot_and_prometheus(tmp_path: Path) -> None:
    s = ComposeSettings(router_port=17447, prometheus_port=19090)
    doc = compose_document(places_spec(3, (0, 27, 54, 80), tmp_path / "ds"), s)
    names = list(doc["services"])
    assert names[:2] == ["router", "gateway"] and names[-1] == "prometheus"
    assert sorted(names[2:-1]) == sorted(f"r{r}-{k}" for r in range(3) for k in PLACES)
    published = {n: svc["ports"] for n, svc in doc["services"].items() if "ports" in svc}
    assert published == {
        "router": ["127.0.0.1:17447:7447"],
        "gateway": ["127.0.0.1:50051:50051"],
        "prometheus": ["127.0.0.1:19090:9090"],
    }
    gateway = doc["services"]["gateway"]["environment"]
    assert gateway["SWARMREC_GRPC_HOST"] == "0.0.0.0" and "SWARMREC_GRPC_PORT" not in gateway  # 50051
    shard = doc["services"]["r2-index-shard"]
    env = shard["environment"]
    assert (env["SWARMREC_ROBOT"], env["SWARMREC_LABEL_BOUNDS"], env["SWARMREC_CONNECT"]) == (
        "2",
        "0,27,54,80",
        "tls/router:7447",
    )
    # Mutual TLS by default: each container mounts its own secrets folder as the PKI.
    assert env["SWARMREC_PKI_DIR"] == "/run/swarmrec/pki" and "SWARMREC_SECURITY" not in env
    assert (env["SWARMREC_DATA_DIR"], env["SWARMREC_METRICS_PORT"], env["SWARMREC_METRICS_HOST"]) == (
        "/var/lib/swarmrec",
        "9464",
        "0.0.0.0",
    )
    # A shard's environment holds its own components' settings only: nothing of cameras.
    assert "SWARMREC_CAMERA_FX" not in env and "SWARMREC_DATASET" not in env
    assert shard["depends_on"] == {"router": {"condition": "service_healthy"}}
    secrets = "./secrets/{}:/run/swarmrec/pki:ro"
    assert shard["volumes"] == [secrets.format("r2-index-shard"), "r2-index-shard-data:/var/lib/swarmrec"]
    detector = doc["services"]["r2-detector"]
    assert detector["volumes"] == [secrets.format("r2-detector"), "./dataset:/data/dataset:ro"]
    assert detector["environment"]["SWARMREC_DATASET"] == "/data/dataset"
    assert "SWARMREC_DATA_DIR" not in detector["environment"]  # not stateful: no volume
    router = doc["services"]["router"]["environment"]
    assert (router["SWARMREC_MODE"], router["SWARMREC_LISTEN"]) == ("router", "tls/0.0.0.0:7447")
    assert sorted(doc["volumes"]) == sorted(
        [f"r{r}-{k}-data" for r in range(3) for k in ("index-shard", "verifier", "descriptor")]
        + ["prometheus-data"]
    )


def test_prometheus_scrapes_every_service_with_its_service_and_robot_labels(tmp_path: Path) -> None:
    doc = prometheus_document(places_spec(2, (0, 40, 80), tmp_path), ComposeSettings())
    (job,) = doc["scrape_configs"]
    targets = {g["targets"][0]: (g["labels"]["service"], g["labels"]["robot"]) for g in job["static_configs"]}
    assert targets == {
        "router:9464": ("router", "0"),
        "gateway:9464": ("gateway", "0"),
        **{f"{service_name(k, r)}:9464": (k, str(r)) for r in range(2) for k in PLACES},
    }


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"project": "My Swarm"}, "project must be letters"),
        ({"project": "Swarm"}, "lower case"),
        ({"router_port": 9090}, "must differ"),
        ({"prometheus_port": 0}, "prometheus_port must be 1 .. 65535"),
    ],
)
def test_compose_settings_refuse_bad_values_with_a_clear_message(
    changes: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        ComposeSettings(**changes)  # type: ignore[arg-type]


@pytest.mark.parametrize("robots", [17, 20])
def test_a_swarm_too_large_for_compose_is_refused(tmp_path: Path, robots: int) -> None:
    spec = places_spec(robots, (), tmp_path)
    with pytest.raises(ConfigError, match=r"1 \.\. 16 robots"):
        write_compose(spec, ComposeSettings(out=tmp_path / "c"))


def test_reading_a_missing_or_foreign_swarm_file_says_what_to_do(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="swarmrec compose up"):
        read_swarm_file(tmp_path)
    (tmp_path / "swarm.json").write_text('{"robots": 4}')
    with pytest.raises(ConfigError, match="not a swarm file"):
        read_swarm_file(tmp_path)


def test_a_places_swarm_copies_its_dataset_and_records_the_run(tmp_path: Path) -> None:
    run = PlacesSettings(source=DatasetSource(frames=50), robots=2, swarm="compose", out=tmp_path)
    spec = prepare(run, dataset_dir=tmp_path / "prepared").spec
    info = write_compose(spec, ComposeSettings(out=tmp_path / "c"), experiment=run.record())
    assert sorted(p.name for p in (tmp_path / "c" / "dataset").iterdir()) == sorted(
        p.name for p in (tmp_path / "prepared").iterdir()
    )
    assert read_swarm_file(tmp_path / "c") == info
    assert PlacesSettings.from_record(info.experiment, out=tmp_path / "r").source == run.source
    assert info.shared_env["SWARMREC_LOCKSTEP"] == "true" and info.kinds == list(PLACES)


def test_a_landmarks_swarm_has_a_classifier_detector_and_a_fusion_service_per_robot(tmp_path: Path) -> None:
    s = ComposeSettings(out=tmp_path, router_port=17447, prometheus_port=19090)
    spec = swarm_spec(LandmarkSettings(out=tmp_path / "r", robots=3, swarm="compose"))
    doc = compose_document(spec, s)
    names = list(doc["services"])
    assert sorted(names[2:-1]) == sorted(f"r{r}-{k}" for r in range(3) for k in ("detector", "fusion"))
    detector = doc["services"]["r1-detector"]
    assert detector["environment"]["SWARMREC_DETECTOR_MODE"] == "classifier"
    assert detector["volumes"] == ["./secrets/r1-detector:/run/swarmrec/pki:ro"]
    assert "SWARMREC_DATASET" not in detector["environment"]
    assert "SWARMREC_LABEL_BOUNDS" not in doc["services"]["r1-fusion"]["environment"]
    assert sorted(doc["volumes"]) == ["prometheus-data"]  # nothing a landmarks robot keeps
    (job,) = prometheus_document(spec, s)["scrape_configs"]
    services = {g["labels"]["service"] for g in job["static_configs"]}
    assert services == {"router", "gateway", "detector", "fusion"}
    info = write_compose(spec, s)
    assert info.workload == "landmarks" and info.kinds == ["fusion", "detector"]
    assert read_swarm_file(tmp_path) == info
    assert not (tmp_path / "dataset").exists()


def test_a_running_swarm_that_is_not_the_runs_spec_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    lm = swarm_spec(LandmarkSettings(out=tmp_path / "r", robots=2, swarm="compose"))
    write_compose(lm, ComposeSettings(out=tmp_path / "lm"))
    places = places_spec(2, (0, 40, 80), tmp_path / "ds")
    deployment = ComposeDeployment(tmp_path / "lm")
    with pytest.raises(ConfigError, match="landmarks workload, not places"):
        deployment.start(places)
    three = swarm_spec(LandmarkSettings(out=tmp_path / "r", robots=3, swarm="compose"))
    with pytest.raises(ConfigError, match="it has 2 robots, not 3"):
        deployment.start(three)
    other_model = swarm_spec(LandmarkSettings(out=tmp_path / "r", robots=2, swarm="compose", model="x.onnx"))
    with pytest.raises(ConfigError, match="SWARMREC_CLASSIFIER_MODEL"):
        deployment.start(other_model)
