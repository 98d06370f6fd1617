"""Settings per component: the four layers, value conversion, flags and variables generated
from one declaration, and the errors a user sees."""

from __future__ import annotations

import argparse
import itertools
from dataclasses import fields
from pathlib import Path

import pytest

from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import (
    BusSettings,
    Config,
    StorageSettings,
    add_flags,
    describe,
    load_config,
    to_env,
    to_flags,
)
from swarmrec.services import registry
from swarmrec.services.settings import (
    DetectorSettings,
    FusionSettings,
    IndexSettings,
    PlaceSettings,
    RgbdSettings,
)

SHARD = (BusSettings, StorageSettings, PlaceSettings)


def parser(components: tuple[type, ...] = SHARD) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="swarmrec serve")
    add_flags(p, components)  # type: ignore[arg-type]
    return p


def flags(*argv: str) -> argparse.Namespace:
    return parser().parse_args(list(argv))


def load(args: argparse.Namespace | None = None, **kwargs: object) -> Config:
    return load_config(SHARD, args, known=registry.all_components(), **kwargs)  # type: ignore[arg-type]


def toml_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(text, encoding="utf-8")
    return path


# --- layering -----------------------------------------------------------------


def test_no_layer_gives_the_documented_defaults() -> None:
    c = load(flags(), env={})
    assert c == Config((BusSettings(), StorageSettings(), PlaceSettings()))
    assert (c.bus.swarm, c.bus.robot, c.bus.n_robots, c.bus.mode, c.bus.connect) == (
        "default",
        0,
        1,
        "client",
        ("tls/127.0.0.1:7447",),
    )


def test_each_layer_overrides_the_ones_below_it(tmp_path: Path) -> None:
    # n_labels is set by the file only, workers up to the file, swarm up to the environment,
    # robot by flags and n_robots by the caller's overrides: each ends with its highest layer.
    path = toml_file(tmp_path, 'workers = 5\nswarm = "file"\nrobot = 1\nn_robots = 4\nn_labels = 40\n')
    env = {"SWARMREC_SWARM": "env", "SWARMREC_ROBOT": "2", "SWARMREC_N_ROBOTS": "3"}
    c = load(flags("--robot", "3", "--n-robots", "5"), env=env, config_file=path, overrides={"n_robots": 6})
    assert (c.get(PlaceSettings).n_labels, c.bus.workers, c.bus.swarm, c.bus.robot, c.bus.n_robots) == (
        40,
        5,
        "env",
        3,
        6,
    )


def test_the_config_flag_names_the_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = 2\nn_robots = 3\n")
    c = load(flags("--config", str(path)), env={})
    assert (c.bus.robot, c.bus.n_robots) == (2, 3)


def test_the_config_argument_wins_over_the_config_flag(tmp_path: Path) -> None:
    flag_file = toml_file(tmp_path, "workers = 7\n")
    arg_file = tmp_path / "other.toml"
    arg_file.write_text("workers = 9\n", encoding="utf-8")
    assert load(flags("--config", str(flag_file)), env={}, config_file=arg_file).bus.workers == 9


def test_the_environment_can_name_the_config_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "workers = 6\n")
    assert load(env={"SWARMREC_CONFIG": str(path)}).bus.workers == 6


def test_one_file_configures_a_whole_robot_each_service_taking_its_own_settings(tmp_path: Path) -> None:
    # A camera setting in a robot's file is ignored by its shard and read by its detector.
    path = toml_file(tmp_path, "robot = 1\nn_robots = 2\ncamera_fx = 500.5\nfusion_law = 'agreement'\n")
    shard = load(env={}, config_file=path)
    assert not shard.has(RgbdSettings) and shard.bus.robot == 1
    components = registry.spec("detector").all_components
    detector = load_config(components, env={}, config_file=path, known=registry.all_components())
    assert detector.get(RgbdSettings).camera_fx == 500.5


def test_an_explicit_empty_environment_ignores_the_process_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SWARMREC_WORKERS", "6")
    monkeypatch.setenv("SWARMREC_CONFIG", str(toml_file(tmp_path, "n_labels = 40\n")))
    c = load(flags(), env={})
    assert (c.bus.workers, c.get(PlaceSettings).n_labels) == (2, 80)


def test_without_an_env_argument_the_process_environment_is_read(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SWARMREC_WORKERS", "6")
    assert load(flags()).bus.workers == 6


def test_a_service_reads_no_variable_of_a_component_it_does_not_have() -> None:
    # SWARMREC_CAMERA_FX is not the shard's: not read, so not an error either.
    assert load(env={"SWARMREC_CAMERA_FX": "not a number"}) == load(env={})


def test_unset_flags_do_not_override_lower_layers() -> None:
    args = flags("--workers", "4")
    assert all(getattr(args, name) is None for name in ("robot", "swarm", "fsync", "connect"))
    c = load(args, env={"SWARMREC_SWARM": "lab"})
    assert (c.bus.workers, c.bus.swarm) == (4, "lab")


# --- conversion -------------------------------------------------------------------


def test_lists_are_comma_separated_in_the_environment_and_flags() -> None:
    env = {"SWARMREC_CONNECT": " tcp/10.0.0.1:7447, tcp/10.0.0.2:7447,"}
    c = load(flags("--n-robots", "2", "--label-bounds", "0,30,80"), env=env)
    assert c.bus.connect == ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447")
    assert c.get(PlaceSettings).label_bounds == (0, 30, 80)


def test_lists_are_toml_arrays_in_the_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, 'connect = ["tcp/a:1", "tcp/b:2"]\nn_robots = 2\nlabel_bounds = [0, 30, 80]\n')
    c = load(env={}, config_file=path)
    assert (c.bus.connect, c.get(PlaceSettings).label_bounds) == (("tcp/a:1", "tcp/b:2"), (0, 30, 80))


@pytest.mark.parametrize(
    ("text", "value"),
    [("1", True), ("true", True), ("Yes", True), (" ON ", True), ("0", False), ("False", False),
     ("no", False), ("off", False)],
)  # fmt: skip
def test_booleans_read_the_usual_words(text: str, value: bool) -> None:
    assert load(env={"SWARMREC_FSYNC": text}).get(StorageSettings).fsync is value


def test_toml_booleans_are_booleans(tmp_path: Path) -> None:
    c = load(env={}, config_file=toml_file(tmp_path, "fsync = true\nlockstep = true\n"))
    assert c.get(PlaceSettings).lockstep and c.get(StorageSettings).fsync


def test_paths_become_paths_and_an_empty_path_is_none() -> None:
    c = load(env={"SWARMREC_DATA_DIR": "/var/lib/swarmrec"})
    assert c.get(StorageSettings).data_dir == Path("/var/lib/swarmrec")
    assert (
        load(flags("--data-dir", ""), env={"SWARMREC_DATA_DIR": "/x"}).get(StorageSettings).data_dir is None
    )


def test_numbers_are_read_from_strings() -> None:
    c = load(flags("--request-timeout-s", "0.5", "--metrics-port", "-1"), env={})
    assert (c.bus.request_timeout_s, c.bus.metrics_port) == (0.5, -1)


def test_an_optional_number_left_empty_is_unset() -> None:
    rgbd = load_config((RgbdSettings,), env={"SWARMREC_CONF_THRESHOLD": ""}).get(RgbdSettings)
    assert rgbd.conf_threshold is None


# --- errors ---------------------------------------------------------------------


def test_an_unknown_key_in_the_file_is_named(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = 1\nn_robots = 2\nrobots = 3\ncolour = 'red'\n")
    with pytest.raises(ConfigError, match=r"robot\.toml: unknown settings colour, robots$"):
        load(env={}, config_file=path)


def test_a_file_that_is_not_toml_is_named(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = = 1\n")
    with pytest.raises(ConfigError, match=r"config file .*robot\.toml is not valid TOML"):
        load(env={}, config_file=path)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot read config file .*absent\.toml"):
        load(env={}, config_file=tmp_path / "absent.toml")


def test_a_bad_boolean_names_the_setting_and_the_value() -> None:
    with pytest.raises(ConfigError, match=r"setting fsync: cannot read 'maybe' \(not a boolean: 'maybe'\)"):
        load(env={"SWARMREC_FSYNC": "maybe"})


def test_a_bad_number_names_the_setting() -> None:
    with pytest.raises(ConfigError, match="setting workers: cannot read 'two'"):
        load(flags("--workers", "two"), env={})


def test_a_float_where_an_integer_is_meant_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"setting workers: cannot read 2\.9 \(not an integer"):
        load(env={}, config_file=toml_file(tmp_path, "workers = 2.9\n"))


@pytest.mark.parametrize(("robot", "n_robots"), [(3, 3), (4, 3)])
def test_a_robot_id_outside_the_swarm_is_refused(robot: int, n_robots: int) -> None:
    with pytest.raises(ConfigError, match=rf"robot must be in \[0, 3\) \(n_robots={n_robots}\), got {robot}"):
        Config.of(BusSettings(robot=robot, n_robots=n_robots))


def test_a_negative_robot_id_is_refused() -> None:
    with pytest.raises(ConfigError, match="robot must be >= 0, got -1"):
        BusSettings(robot=-1, n_robots=3)


def test_index_shards_may_have_ids_beyond_the_robots_up_to_max_shards() -> None:
    index = IndexSettings(max_shards=6)
    assert Config.of(BusSettings(robot=5, n_robots=3), index).bus.robot == 5
    with pytest.raises(ConfigError, match=r"robot must be in \[0, 6\)"):
        Config.of(BusSettings(robot=6, n_robots=3), index)


@pytest.mark.parametrize(
    "bounds",
    [
        (0, 40),  # one boundary short for 2 robots
        (0, 40, 79),  # does not end at n_labels
        (1, 40, 80),  # does not start at 0
        (0, 40, 40, 80),  # too many
        (0, 50, 40),  # decreasing
    ],
)
def test_label_bounds_that_are_not_n_robots_ranges_are_refused(bounds: tuple[int, ...]) -> None:
    with pytest.raises(ConfigError, match=r"label_bounds must be 3 non-decreasing values from 0 to 80"):
        Config.of(BusSettings(n_robots=2), PlaceSettings(label_bounds=bounds))


def test_label_bounds_of_n_robots_ranges_are_accepted() -> None:
    c = Config.of(BusSettings(n_robots=3), PlaceSettings(label_bounds=(0, 1, 79, 80)))
    assert c.get(PlaceSettings).bounds(c.bus).tolist() == [0, 1, 79, 80]
    # An empty range is a robot that owns no label of its own.
    c = Config.of(BusSettings(n_robots=3), PlaceSettings(label_bounds=(0, 40, 40, 80)))
    assert c.get(PlaceSettings).bounds(c.bus).tolist() == [0, 40, 40, 80]


def test_more_robots_than_labels_get_the_papers_split_with_empty_ranges() -> None:
    # 100 robots over 80 labels: integer linspace(0, 80, 101), as the published scripts;
    # e.g. robots 0 and 1 get [0, 0) and [0, 1).
    c = Config.of(BusSettings(n_robots=100), PlaceSettings())
    b = c.get(PlaceSettings).bounds(c.bus).tolist()
    assert len(b) == 101 and b[0] == 0 and b[-1] == 80
    assert b[:6] == [0, 0, 1, 2, 3, 4]
    assert sum(1 for x, y in itertools.pairwise(b) if x == y) == 20


def test_the_balanced_preset_needs_explicit_label_bounds() -> None:
    with pytest.raises(ConfigError, match="balanced preset needs explicit label_bounds"):
        Config.of(BusSettings(n_robots=2), PlaceSettings(preset="balanced"))


@pytest.mark.parametrize("name", ["lab/a", "lab*", "*", "**", "", "a" * 65, "lab a", "lab$"])
def test_a_swarm_name_that_is_not_one_plain_key_segment_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match="swarm name must be 1-64 of"):
        load(env={"SWARMREC_SWARM": name})


def test_a_router_without_a_listen_endpoint_is_refused() -> None:
    with pytest.raises(ConfigError, match="a router needs at least one --listen endpoint"):
        load(flags("--mode", "router"), env={})
    c = load(flags("--mode", "router", "--listen", "tcp/0.0.0.0:7447"), env={})
    assert c.bus.listen == ("tcp/0.0.0.0:7447",)


def test_a_client_without_a_connect_endpoint_is_refused() -> None:
    with pytest.raises(ConfigError, match="a client needs at least one --connect endpoint"):
        load(flags("--connect", ""), env={})


def test_an_unknown_mode_is_refused() -> None:
    with pytest.raises(ConfigError, match="mode must be client, peer or router, got 'server'"):
        load(flags("--mode", "server"), env={})


def test_an_unknown_preset_is_refused_naming_the_component() -> None:
    with pytest.raises(ConfigError, match=r"invalid place recognition settings: .*'nonsense'"):
        load(flags("--preset", "nonsense"), env={})


def test_every_problem_of_a_component_is_reported_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        BusSettings(swarm="a/b", workers=0, metrics_port=70000)
    text = str(err.value)
    assert text.startswith("invalid bus settings: ")
    for part in ("swarm name", "workers must be >= 1, got 0", "metrics_port must be -1 .. 65535, got 70000"):
        assert part in text


def test_with_validates_the_copy() -> None:
    s = BusSettings(n_robots=4)
    assert s.with_(robot=3).robot == 3
    with pytest.raises(ConfigError, match="robot must be >= 0"):
        s.with_(robot=-4)


def test_asking_a_config_for_a_component_it_lacks_says_so() -> None:
    with pytest.raises(ConfigError, match="no fusion settings here"):
        load(env={}).get(FusionSettings)


def test_replace_swaps_a_component_and_checks_the_whole_again() -> None:
    c = Config.of(BusSettings(n_robots=2), PlaceSettings(label_bounds=(0, 40, 80)))
    with pytest.raises(ConfigError, match="label_bounds must be 4"):
        c.replace(BusSettings(n_robots=3))


# --- one declaration, every form ------------------------------------------------


def test_setting_names_are_unique_across_every_component() -> None:
    names = [f.name for comp in registry.all_components() for f in fields(comp)]
    assert len(names) == len(set(names)), sorted(n for n in names if names.count(n) > 1)


def test_every_setting_has_help() -> None:
    missing = [f"{c.__name__}.{i.name}" for c in registry.all_components() for i in describe(c) if not i.help]
    assert missing == []


def every_component_set_away_from_its_defaults(tmp_path: Path) -> Config:
    return Config.of(
        BusSettings(
            swarm="lab-2",
            robot=2,
            n_robots=3,
            mode="router",
            connect=(),
            listen=("tcp/0.0.0.0:7447", "udp/0.0.0.0:7447"),
            metrics_port=-1,
            metrics_host="0.0.0.0",
            workers=4,
            request_timeout_s=0.25,
            max_message_bytes=4096,
            log_level="DEBUG",
        ),
        StorageSettings(data_dir=tmp_path / "data", fsync=True),
        PlaceSettings(
            preset="balanced",
            n_labels=60,
            label_bounds=(0, 10, 35, 60),
            lockstep=True,
            loop_closure_min_score=0.125,
        ),
        DetectorSettings(detector_mode="rgbd", dataset="frames", labels_file=None, frames_per_robot=17),
        RgbdSettings(
            detector_model="models/mine.onnx",
            conf_threshold=0.375,
            iou_threshold=0.5,
            detector_threads=2,
            camera_fx=517.3,
            camera_fy=516.5,
            camera_cx=318.6,
            camera_cy=255.3,
            depth_scale=1000.0,
            rgbd_max_dt=0.03,
        ),
    )


def test_flags_round_trip_through_the_parser(tmp_path: Path) -> None:
    config = every_component_set_away_from_its_defaults(tmp_path)
    components = tuple(type(p) for p in config.parts)
    argv = [flag for part in config.parts for flag in to_flags(part)]
    assert "--labels-file" not in argv  # None is left to the lower layers
    assert load_config(components, parser(components).parse_args(argv), env={}) == config


def test_variables_round_trip_through_the_environment(tmp_path: Path) -> None:
    config = every_component_set_away_from_its_defaults(tmp_path)
    env = {k: v for part in config.parts for k, v in to_env(part).items()}
    assert env["SWARMREC_LABEL_BOUNDS"] == "0,10,35,60" and env["SWARMREC_LOCKSTEP"] == "true"
    assert load_config(tuple(type(p) for p in config.parts), env=env) == config
