"""Service settings: the four layers, value conversion and the errors a user sees."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from swarmrec.errors import ConfigError
from swarmrec.services.config import (
    ServiceSettings,
    add_arguments,
    load_settings,
    settings_to_flags,
)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="swarmrec serve")
    add_arguments(p)
    return p


def flags(*argv: str) -> argparse.Namespace:
    return parser().parse_args(list(argv))


def toml_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(text, encoding="utf-8")
    return path


# --- layering -----------------------------------------------------------------


def test_no_layer_gives_the_documented_defaults() -> None:
    s = load_settings(flags(), env={})
    assert s == ServiceSettings()
    assert (s.swarm, s.robot, s.n_robots, s.mode, s.connect) == (
        "default",
        0,
        1,
        "client",
        ("tcp/127.0.0.1:7447",),
    )


def test_each_layer_overrides_the_ones_below_it(tmp_path: Path) -> None:
    # n_labels is set by defaults only, workers up to the file, swarm up to the
    # environment and robot by all four layers: each ends with its highest layer.
    path = toml_file(tmp_path, 'workers = 5\nswarm = "file"\nrobot = 1\nn_robots = 4\n')
    defaults = {"n_labels": 40, "workers": 3, "swarm": "defaults", "robot": 0}
    env = {"SWARMREC_SWARM": "env", "SWARMREC_ROBOT": "2"}
    s = load_settings(flags("--robot", "3"), env=env, config=path, defaults=defaults)
    assert (s.n_labels, s.workers, s.swarm, s.robot, s.n_robots) == (40, 5, "env", 3, 4)


def test_the_config_flag_names_the_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = 2\nn_robots = 3\n")
    s = load_settings(flags("--config", str(path)), env={})
    assert (s.robot, s.n_robots) == (2, 3)


def test_the_config_argument_wins_over_the_config_flag(tmp_path: Path) -> None:
    flag_file = toml_file(tmp_path, "workers = 7\n")
    arg_file = tmp_path / "other.toml"
    arg_file.write_text("workers = 9\n", encoding="utf-8")
    assert load_settings(flags("--config", str(flag_file)), env={}, config=arg_file).workers == 9


def test_the_environment_can_name_the_config_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "workers = 6\n")
    assert load_settings(env={"SWARMREC_CONFIG": str(path)}).workers == 6


def test_an_explicit_empty_environment_ignores_the_process_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SWARMREC_WORKERS", "6")
    monkeypatch.setenv("SWARMREC_CONFIG", str(toml_file(tmp_path, "n_labels = 40\n")))
    s = load_settings(flags(), env={})
    assert (s.workers, s.n_labels) == (2, 80)


def test_without_an_env_argument_the_process_environment_is_read(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SWARMREC_WORKERS", "6")
    assert load_settings(flags()).workers == 6


def test_unset_flags_do_not_override_lower_layers() -> None:
    args = flags("--workers", "4")
    assert all(getattr(args, name) is None for name in ("robot", "swarm", "fsync", "connect"))
    s = load_settings(args, env={"SWARMREC_SWARM": "lab"})
    assert (s.workers, s.swarm) == (4, "lab")


# --- conversion -------------------------------------------------------------------


def test_lists_are_comma_separated_in_the_environment_and_flags() -> None:
    env = {"SWARMREC_CONNECT": " tcp/10.0.0.1:7447, tcp/10.0.0.2:7447,"}
    s = load_settings(flags("--n-robots", "2", "--label-bounds", "0,30,80"), env=env)
    assert s.connect == ("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447")
    assert s.label_bounds == (0, 30, 80)


def test_lists_are_toml_arrays_in_the_file(tmp_path: Path) -> None:
    path = toml_file(tmp_path, 'connect = ["tcp/a:1", "tcp/b:2"]\nn_robots = 2\nlabel_bounds = [0, 30, 80]\n')
    s = load_settings(env={}, config=path)
    assert (s.connect, s.label_bounds) == (("tcp/a:1", "tcp/b:2"), (0, 30, 80))


@pytest.mark.parametrize(
    ("text", "value"),
    [("1", True), ("true", True), ("Yes", True), (" ON ", True), ("0", False), ("False", False),
     ("no", False), ("off", False)],
)  # fmt: skip
def test_booleans_read_the_usual_words(text: str, value: bool) -> None:
    assert load_settings(env={"SWARMREC_FSYNC": text}).fsync is value


def test_toml_booleans_are_booleans(tmp_path: Path) -> None:
    assert load_settings(env={}, config=toml_file(tmp_path, "fsync = true\nlockstep = true\n")).lockstep


def test_paths_become_paths_and_an_empty_path_is_none() -> None:
    assert load_settings(env={"SWARMREC_DATA_DIR": "/var/lib/swarmrec"}).data_dir == Path("/var/lib/swarmrec")
    assert load_settings(flags("--data-dir", ""), env={"SWARMREC_DATA_DIR": "/x"}).data_dir is None


def test_numbers_are_read_from_strings() -> None:
    s = load_settings(flags("--request-timeout-s", "0.5", "--metrics-port", "-1"), env={})
    assert (s.request_timeout_s, s.metrics_port) == (0.5, -1)


# --- errors ---------------------------------------------------------------------


def test_an_unknown_key_in_the_file_is_named(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = 1\nn_robots = 2\nrobots = 3\ncolour = 'red'\n")
    with pytest.raises(ConfigError, match=r"robot\.toml: unknown settings colour, robots$"):
        load_settings(env={}, config=path)


def test_a_file_that_is_not_toml_is_named(tmp_path: Path) -> None:
    path = toml_file(tmp_path, "robot = = 1\n")
    with pytest.raises(ConfigError, match=r"config file .*robot\.toml is not valid TOML"):
        load_settings(env={}, config=path)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot read config file .*absent\.toml"):
        load_settings(env={}, config=tmp_path / "absent.toml")


def test_a_bad_boolean_names_the_setting_and_the_value() -> None:
    with pytest.raises(ConfigError, match=r"setting fsync: cannot read 'maybe' \(not a boolean: 'maybe'\)"):
        load_settings(env={"SWARMREC_FSYNC": "maybe"})


def test_a_bad_number_names_the_setting() -> None:
    with pytest.raises(ConfigError, match="setting workers: cannot read 'two'"):
        load_settings(flags("--workers", "two"), env={})


@pytest.mark.parametrize(("robot", "n_robots"), [(3, 3), (4, 3), (-1, 3)])
def test_a_robot_id_outside_the_swarm_is_refused(robot: int, n_robots: int) -> None:
    with pytest.raises(ConfigError, match=rf"robot must be in \[0, n_robots={n_robots}\), got {robot}"):
        ServiceSettings(robot=robot, n_robots=n_robots)


@pytest.mark.parametrize(
    "bounds",
    [
        (0, 40),  # one boundary short for 2 robots
        (0, 40, 79),  # does not end at n_labels
        (1, 40, 80),  # does not start at 0
        (0, 40, 40, 80),  # too many, and an empty range
        (0, 50, 40),  # decreasing
    ],
)
def test_label_bounds_that_are_not_n_robots_ranges_are_refused(bounds: tuple[int, ...]) -> None:
    with pytest.raises(ConfigError, match=r"label_bounds must be 3 increasing values from 0 to 80"):
        ServiceSettings(n_robots=2, label_bounds=bounds)


def test_label_bounds_of_n_robots_ranges_are_accepted() -> None:
    assert ServiceSettings(n_robots=3, label_bounds=(0, 1, 79, 80)).label_bounds == (0, 1, 79, 80)


@pytest.mark.parametrize("name", ["lab/a", "lab*", "*", "**", "", "a" * 65, "lab a", "lab$"])
def test_a_swarm_name_that_is_not_one_plain_key_segment_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match="swarm name must be 1-64 of"):
        load_settings(env={"SWARMREC_SWARM": name})


def test_a_router_without_a_listen_endpoint_is_refused() -> None:
    with pytest.raises(ConfigError, match="a router needs at least one --listen endpoint"):
        load_settings(flags("--mode", "router"), env={})
    s = load_settings(flags("--mode", "router", "--listen", "tcp/0.0.0.0:7447"), env={})
    assert s.listen == ("tcp/0.0.0.0:7447",)


def test_a_client_without_a_connect_endpoint_is_refused() -> None:
    with pytest.raises(ConfigError, match="a client needs at least one --connect endpoint"):
        load_settings(flags("--connect", ""), env={})


def test_an_unknown_mode_is_refused() -> None:
    with pytest.raises(ConfigError, match="mode must be client, peer or router, got 'server'"):
        load_settings(flags("--mode", "server"), env={})


def test_an_unknown_preset_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"invalid settings: .*'nonsense'"):
        load_settings(flags("--preset", "nonsense"), env={})


def test_every_problem_is_reported_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        ServiceSettings(swarm="a/b", workers=0, metrics_port=70000)
    text = str(err.value)
    assert text.startswith("invalid settings: ")
    for part in ("swarm name", "workers must be >= 1, got 0", "metrics_port must be -1 .. 65535, got 70000"):
        assert part in text


def test_with_validates_the_copy() -> None:
    s = ServiceSettings(n_robots=4)
    assert s.with_(robot=3).robot == 3
    with pytest.raises(ConfigError, match="robot must be in"):
        s.with_(robot=4)


# --- settings to flags ------------------------------------------------------------


def test_settings_to_flags_round_trips_through_the_parser(tmp_path: Path) -> None:
    settings = ServiceSettings(
        swarm="lab-2",
        robot=2,
        n_robots=3,
        mode="router",
        connect=(),
        listen=("tcp/0.0.0.0:7447", "udp/0.0.0.0:7447"),
        preset="balanced",
        n_labels=60,
        label_bounds=(0, 10, 35, 60),
        data_dir=tmp_path / "data",
        fsync=True,
        metrics_port=-1,
        metrics_host="0.0.0.0",
        workers=4,
        request_timeout_s=0.25,
        lockstep=True,
        max_message_bytes=4096,
        loop_closure_min_score=0.125,
        dataset="",
        labels_file=None,
        frames_per_robot=17,
        detector_mode="rgbd",
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
        classifier_model="models/landmarks.onnx",
        log_level="DEBUG",
    )
    names = list(ServiceSettings.__dataclass_fields__)
    argv = settings_to_flags(settings, names)
    assert "--labels-file" not in argv  # None is left to the lower layers
    assert load_settings(parser().parse_args(argv), env={}) == settings


def test_settings_to_flags_gives_only_the_names_asked_for() -> None:
    argv = settings_to_flags(ServiceSettings(robot=1, n_robots=2), ["robot", "connect", "fsync"])
    assert argv == ["--robot", "1", "--connect", "tcp/127.0.0.1:7447", "--fsync", "False"]
