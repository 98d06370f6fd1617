"""Handing a kind to the compiled host (swarmrec.services.compiled): which kinds go, what
the binary is told, where it is found, and the clear error when it is not built."""

from __future__ import annotations

import itertools
import json
import os
import stat
from pathlib import Path
from typing import Any

import pytest
import zenoh

from swarmrec.core.placement import ring
from swarmrec.core.presets import get_preset
from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import (
    SINGLE_RUNTIME_TX_QUEUE,
    BusSettings,
    Config,
    SecuritySettings,
    StorageSettings,
)
from swarmrec.services import compiled, registry
from swarmrec.services.settings import DetectorSettings, IndexSettings, PlaceSettings, VprSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.placement import placement_from_proto


def config(data_plane: str, **place: object) -> Config:
    return Config(
        (
            BusSettings(
                swarm="lab", robot=3, n_robots=5, data_plane=data_plane, connect=("tcp/127.0.0.1:7447",)
            ),  # type: ignore[arg-type]
            SecuritySettings(security="insecure", insecure_reason="unit test"),
            StorageSettings(data_dir=Path("/var/lib/x")),
            PlaceSettings(**place),  # type: ignore[arg-type]
        )
    )


def test_only_kinds_with_a_compiled_implementation_go_and_only_when_the_setting_says_so() -> None:
    compiled_kinds = [k for k, e in registry.REGISTRY.items() if e.compiled]
    assert compiled_kinds == ["router", "detector", "descriptor", "index-shard", "verifier"]
    verifier = registry.spec("verifier")
    assert compiled.is_compiled(config("compiled"), verifier.compiled_for(config("compiled")))
    assert not compiled.is_compiled(config("python"), verifier.compiled_for(config("python")))
    assert not compiled.is_compiled(
        config("compiled"), registry.spec("place-owner").compiled_for(config("compiled"))
    )


@pytest.mark.parametrize(("mode", "served"), [("replay", True), ("rgbd", False), ("classifier", False)])
def test_a_detector_is_compiled_in_its_replay_mode_only(mode: str, served: bool) -> None:
    detector = registry.spec("detector")
    cfg = config("compiled").replace(DetectorSettings(detector_mode=mode))  # type: ignore[arg-type]
    assert detector.compiled_for(cfg) is served
    assert compiled.is_compiled(cfg, detector.compiled_for(cfg)) is served
    # The contract page says so.
    assert detector.compiled_when is not None and "replay mode only" in detector.compiled_when.doc


def test_a_replaying_detector_is_handed_the_bytes_the_python_codec_puts_on_the_wire(tmp_path: Path) -> None:
    """Robot 3 of 5 plays its fifth of the frames; each frame's bytes are what
    ``constellation_to_proto`` makes (the Python detector's), or, for one the codec refuses,
    the reason."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(10):
        x = 3.0e6 if i == 7 else 0.25 * i
        (folder / f"{100 + i}.5.txt").write_text(f"chair {x!r} 1.0 2.0\ncup 0.5 0.5 0.5\n", encoding="utf-8")
    cfg = config("compiled").replace(DetectorSettings(dataset=str(folder), outbox_retry_s=2.0))
    spec = compiled.host_spec([registry.hosted("detector", cfg)])["services"][0]["detector"]
    assert spec["dataset"] == str(folder) and spec["outbox_retry_s"] == 2.0
    assert spec["process_timeout_s"] == 4 * BusSettings().request_timeout_s
    frames = spec["frames"]
    assert len(frames) == 2  # robot 3 of 5: frames 6 and 7
    first = pb.Constellation.FromString(bytes.fromhex(frames[0]["wire"]))
    assert (first.robot_id, first.frame_index, first.frame_id) == (3, 0, "106.5")
    assert list(first.labels) == [56, 41] and list(first.positions_mm) == [1500, 1000, 2000, 500, 500, 500]
    assert frames[1] == {
        "unsendable": "object 0 at [3000000.0, 1.0, 2.0] m is out of the int32 millimetre range"
    }


def test_a_replaying_detector_for_full_image_recognition_is_refused_before_it_starts(tmp_path: Path) -> None:
    cfg = config("compiled").replace(
        DetectorSettings(dataset=str(tmp_path)), VprSettings(place_method="dvpr")
    )
    with pytest.raises(ConfigError, match="run the detector in rgbd mode"):
        compiled.host_spec([registry.hosted("detector", cfg)])


def test_compiled_shards_keep_a_python_process_for_their_coordinator_and_time_to_drain() -> None:
    verifier = registry.hosted("verifier", config("compiled"))
    shard = registry.hosted("index-shard", config("compiled"))
    assert compiled.index_shards([verifier]) == [] and compiled.index_shards([verifier, shard]) == [shard]
    assert compiled.stop_timeout_s([verifier]) == 10.0
    assert compiled.stop_timeout_s([shard]) == 10.0 + IndexSettings().drain_timeout_s


def test_a_shard_is_told_its_groups_and_the_placement_it_starts_from() -> None:
    bounds = (0, 10, 20, 30, 45, 60)
    (service,) = compiled.host_spec(
        [registry.hosted("index-shard", config("compiled", n_labels=60, label_bounds=bounds))]
    )["services"]
    index = service["index"]
    assert index["groups"] == [[0, 10], [10, 20], [20, 30], [30, 45], [45, 60]]
    assert index["n_ret"] == get_preset("paper").n_ret and index["lockstep"] is False
    first = placement_from_proto(pb.Placement.FromString(bytes(index["initial_placement"])), 60)
    groups = tuple(itertools.pairwise(bounds))
    assert first == ring(groups, range(5), replicas=IndexSettings().replicas)
    assert first.version == 0


def test_a_compiled_kind_is_hosted_without_loading_its_python_class() -> None:
    hosted = registry.hosted("verifier", config("compiled"))
    with pytest.raises(ConfigError, match="compiled host"):
        hosted.factory(None)  # type: ignore[arg-type]
    assert registry.hosted("verifier", config("python")).factory.__name__ == "Verifier"


def test_the_binary_is_told_every_resolved_setting_and_the_zenoh_configuration() -> None:
    spec = compiled.host_spec(
        [
            registry.hosted(
                "verifier",
                config("compiled", preset="balanced", n_labels=60, label_bounds=(0, 10, 20, 30, 45, 60)),
            )
        ]
    )
    json.dumps(spec)  # it travels as JSON
    (service,) = spec["services"]
    assert service["kind"] == "verifier" and service["wire_kind"] == registry.spec("verifier").wire
    assert (service["swarm"], service["robot"], service["n_robots"]) == ("lab", 3, 5)
    assert service["data_dir"] == "/var/lib/x"
    places = service["places"]
    # The balanced preset searches the nearest vector within a label; d and min_common are the preset's.
    assert (places["n_labels"], places["same_label_only"], places["d"], places["min_common"]) == (
        60,
        True,
        0.25,
        3,
    )
    assert places["verify_max_frames"] == PlaceSettings().verify_max_frames
    assert spec["zenoh"]["mode"] == "client"
    assert spec["zenoh"]["connect"]["endpoints"] == ["tcp/127.0.0.1:7447"]
    assert spec["metrics_port"] == 0 and spec["version"]
    # The compiled host runs zenoh on one thread: its send queue holds a ~1 MB message.
    assert spec["zenoh"]["transport"]["link"]["tx"]["queue"]["size"]["data"] == SINGLE_RUNTIME_TX_QUEUE


def test_a_router_is_handed_no_place_settings_and_keeps_zenohs_send_queue() -> None:
    cfg = Config(
        (
            BusSettings(swarm="lab", listen=("tcp/127.0.0.1:0",)),
            SecuritySettings(security="insecure", insecure_reason="unit test"),
        )
    )
    spec = compiled.host_spec([registry.hosted("router", cfg)])
    (service,) = spec["services"]
    assert service["kind"] == "router" and "places" not in service
    assert spec["zenoh"]["mode"] == "router"

    # It runs zenoh's pools (the binary leaves ZENOH_RUNTIME unset for it): zenoh's own queue.
    def data_queue(conf: dict[str, Any]) -> int:
        return int(conf["transport"]["link"]["tx"]["queue"]["size"]["data"])

    assert data_queue(spec["zenoh"]) == data_queue(json.loads(str(zenoh.Config()))) != SINGLE_RUNTIME_TX_QUEUE


def test_a_host_of_fifty_shards_is_handed_its_spec_in_a_file(monkeypatch: pytest.MonkeyPatch) -> None:
    """Linux takes at most 128 kB an argument: fifty shards' settings are more."""
    monkeypatch.setattr(compiled, "binary", lambda: Path("/usr/bin/true"))
    base = config("compiled")
    hosted = [
        registry.hosted("index-shard", base.replace(base.bus.with_(robot=r, n_robots=100))) for r in range(50)
    ]
    argv = compiled._argv(hosted)
    assert argv[:3] == ["/usr/bin/true", "host", "--spec-file"]
    path = Path(argv[3])
    try:
        text = path.read_text()
        assert len(text) > 128 * 1024
        spec = json.loads(text)
        assert [s["robot"] for s in spec["services"]] == list(range(50))
        assert spec["coordinator"] == [] and spec["die_with_parent"] is False
    finally:
        path.unlink()


def test_the_binary_is_found_where_named_and_a_missing_one_says_how_to_build_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    exe = tmp_path / "swarmrec-dataplane"
    exe.write_text("#!/bin/sh\n")
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv(compiled.ENV_VAR, str(exe))
    assert compiled.binary() == exe
    monkeypatch.setenv(compiled.ENV_VAR, str(tmp_path / "missing"))
    monkeypatch.setattr(compiled, "candidates", lambda: [tmp_path / "missing"])
    with pytest.raises(ConfigError, match="make dataplane") as e:
        compiled.binary()
    assert "missing" in str(e.value) and "python" in str(e.value)
    assert os.environ[compiled.ENV_VAR].endswith("missing")


def test_a_service_process_gets_the_zenoh_runtime_its_settings_name_unless_the_environment_does(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from swarmrec.runtime.runner import choose_zenoh_runtime
    from swarmrec.runtime.settings import SINGLE_THREAD_RUNTIME

    # choose_zenoh_runtime writes os.environ itself, behind monkeypatch's back: the whole
    # environment is restored at the end (a ZENOH_RUNTIME left set here once reached every
    # router later tests started, and a router on one thread stalls).
    monkeypatch.setattr(os, "environ", os.environ.copy())
    monkeypatch.delenv("ZENOH_RUNTIME", raising=False)
    choose_zenoh_runtime(BusSettings(zenoh_runtime="pools"))
    assert "ZENOH_RUNTIME" not in os.environ  # zenoh's own pools: nothing to say
    choose_zenoh_runtime(BusSettings(zenoh_runtime="single"))
    assert os.environ["ZENOH_RUNTIME"] == SINGLE_THREAD_RUNTIME
    monkeypatch.delenv("ZENOH_RUNTIME")
    router = BusSettings(zenoh_runtime="single", mode="router", listen=("tcp/127.0.0.1:7447",))
    choose_zenoh_runtime(router)
    assert "ZENOH_RUNTIME" not in os.environ  # a router keeps zenoh's pools
    monkeypatch.setenv("ZENOH_RUNTIME", "(app:(worker_threads:2))")
    choose_zenoh_runtime(BusSettings(zenoh_runtime="single"))
    assert os.environ["ZENOH_RUNTIME"] == "(app:(worker_threads:2))"
