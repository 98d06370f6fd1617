"""The generated compose and Prometheus files, and the YAML writer behind them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from swarmrec.errors import ConfigError
from swarmrec.swarm.compose import (
    ComposeSettings,
    compose_document,
    prometheus_document,
    read_swarm_file,
    render_yaml,
    service_name,
    write_compose,
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


def test_compose_has_a_router_four_services_per_robot_and_prometheus() -> None:
    s = ComposeSettings(robots=3, router_port=17447, prometheus_port=19090)
    doc = compose_document(s, n_labels=80, bounds=[0, 27, 54, 80])
    names = list(doc["services"])
    assert names[0] == "router" and names[-1] == "prometheus"
    assert sorted(names[1:-1]) == sorted(
        f"r{r}-{k}" for r in range(3) for k in ("detector", "descriptor", "index-shard", "verifier")
    )
    published = {n: svc["ports"] for n, svc in doc["services"].items() if "ports" in svc}
    assert published == {"router": ["127.0.0.1:17447:7447"], "prometheus": ["127.0.0.1:19090:9090"]}
    shard = doc["services"]["r2-index-shard"]
    assert shard["environment"]["SWARMREC_ROBOT"] == "2"
    assert shard["environment"]["SWARMREC_LABEL_BOUNDS"] == "0,27,54,80"
    assert shard["environment"]["SWARMREC_CONNECT"] == "tcp/router:7447"
    assert shard["depends_on"] == {"router": {"condition": "service_healthy"}}
    assert shard["volumes"] == ["r2-index-shard-data:/var/lib/swarmrec"]
    assert doc["services"]["r2-detector"]["volumes"] == ["./dataset:/data/dataset:ro"]
    assert sorted(doc["volumes"]) == sorted(
        [f"r{r}-{k}-data" for r in range(3) for k in ("index-shard", "verifier", "descriptor")]
        + ["prometheus-data"]
    )


def test_prometheus_scrapes_every_service_with_its_service_and_robot_labels() -> None:
    doc = prometheus_document(ComposeSettings(robots=2))
    (job,) = doc["scrape_configs"]
    targets = {g["targets"][0]: (g["labels"]["service"], g["labels"]["robot"]) for g in job["static_configs"]}
    assert targets == {
        "router:9464": ("router", "0"),
        **{
            f"{service_name(k, r)}:9464": (k, str(r))
            for r in range(2)
            for k in ("index-shard", "verifier", "descriptor", "detector")
        },
    }


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"robots": 0}, "robots must be 1 .. 16"),
        ({"robots": 17}, "robots must be 1 .. 16"),
        ({"project": "My Swarm"}, "project must be letters"),
        ({"project": "Swarm"}, "lower case"),
        ({"router_port": 9090}, "must differ"),
        ({"prometheus_port": 0}, "prometheus_port must be 1 .. 65535"),
        ({"swarm": "a/b"}, "swarm name"),
    ],
)
def test_compose_settings_refuse_bad_values_with_a_clear_message(
    changes: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        ComposeSettings(**changes)  # type: ignore[arg-type]


def test_reading_a_missing_or_foreign_swarm_file_says_what_to_do(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="swarmrec compose up"):
        read_swarm_file(tmp_path)
    (tmp_path / "swarm.json").write_text('{"robots": 4}')
    with pytest.raises(ConfigError, match="not a swarm file"):
        read_swarm_file(tmp_path)


def test_a_landmarks_swarm_has_a_classifier_detector_and_a_fusion_service_per_robot(tmp_path: Path) -> None:
    s = ComposeSettings(
        robots=3, workload="landmarks", out=tmp_path, router_port=17447, prometheus_port=19090
    )
    doc = compose_document(s, n_labels=0, bounds=[])
    names = list(doc["services"])
    assert sorted(names[1:-1]) == sorted(f"r{r}-{k}" for r in range(3) for k in ("detector", "fusion"))
    detector = doc["services"]["r1-detector"]
    assert detector["environment"]["SWARMREC_DETECTOR_MODE"] == "classifier"
    assert "volumes" not in detector and "SWARMREC_DATASET" not in detector["environment"]
    assert "SWARMREC_LABEL_BOUNDS" not in doc["services"]["r1-fusion"]["environment"]
    assert sorted(doc["volumes"]) == ["prometheus-data"]  # nothing a landmarks robot keeps
    (job,) = prometheus_document(s)["scrape_configs"]
    assert {g["labels"]["service"] for g in job["static_configs"]} == {"router", "detector", "fusion"}
    info = write_compose(s)
    assert info.workload == "landmarks" and info.services == ("fusion", "detector") and info.dataset == ""
    assert read_swarm_file(tmp_path) == info
    assert not (tmp_path / "dataset").exists()


def test_a_landmarks_swarm_needs_two_robots_and_workloads_are_named() -> None:
    with pytest.raises(ConfigError, match="at least 2 robots"):
        ComposeSettings(robots=1, workload="landmarks")
    with pytest.raises(ConfigError, match="workload"):
        ComposeSettings(workload="everything")


def test_each_workload_refuses_the_other_ones_swarm(tmp_path: Path) -> None:
    from swarmrec.swarm.attached import main_attached
    from swarmrec.swarm.landmarks import LandmarkSettings, run_simulation

    write_compose(ComposeSettings(robots=2, workload="landmarks", out=tmp_path / "lm"))
    with pytest.raises(ConfigError, match="swarmrec landmarks --attach"):
        main_attached(tmp_path / "lm", out=tmp_path / "report")
    write_compose(ComposeSettings(robots=2, frames=50, out=tmp_path / "pl"))
    with pytest.raises(ConfigError, match="--workload landmarks"):
        run_simulation(
            LandmarkSettings(out=tmp_path / "r", robots=2, configurations=1), attach=tmp_path / "pl"
        )
    with pytest.raises(ConfigError, match="--robots 2"):
        run_simulation(
            LandmarkSettings(out=tmp_path / "r", robots=3, configurations=1), attach=tmp_path / "lm"
        )
