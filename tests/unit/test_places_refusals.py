"""Settings a places run cannot honour are refused before it writes anything.

A user who typed a link setting the run cannot emulate gets one error, and neither a
half-written run folder nor the loss of an earlier run's stores or logs."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmrec.deployments.links import LinkSpec
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.errors import ConfigError, MalformedLineError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings, main


def settings(out: Path, **changes: object) -> PlacesSettings:
    base = PlacesSettings(source=DatasetSource(frames=40), robots=2, out=out, progress=False, plots=False)
    return base.with_(**changes)


def test_links_with_several_robots_a_process_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="emulated links are per robot"):
        LocalSettings(hosting="robots:2", link=LinkSpec(rate_kbps=50))


def test_a_bad_schedule_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    out = tmp_path / "run"
    earlier = out / "data" / "robot0" / "index-shard" / "store.log"
    earlier.parent.mkdir(parents=True)
    earlier.write_bytes(b"an earlier run's records")
    schedule = tmp_path / "schedule.csv"
    schedule.write_text("start,end,robot\n5,ten,1\n")

    with pytest.raises(MalformedLineError, match=r"schedule\.csv"):
        LocalDeployment.for_run(out, LocalSettings(hosting="robot", schedule=schedule))

    assert earlier.read_bytes() == b"an earlier run's records"
    assert not (out / "dataset").exists()


def test_a_schedule_in_steps_with_a_free_replay_leaves_an_earlier_run_as_it_was(tmp_path: Path) -> None:
    out = tmp_path / "run"
    earlier_log = out / "data" / "robot0" / "verifier" / "verifier.log"
    earlier_log.parent.mkdir(parents=True)
    earlier_log.write_text("an earlier run's log")
    schedule = tmp_path / "schedule.csv"
    schedule.write_text("start,end,robot\n5,10,1\n")
    deployment = LocalDeployment.for_run(out, LocalSettings(hosting="robot", schedule=schedule))

    with pytest.raises(ConfigError, match="a schedule in steps needs a lock-step replay"):
        main(settings(out, pace="fast"), deployment)

    # Refused before the swarm started: the earlier run's files are as they were, nothing new written.
    assert earlier_log.read_text() == "an earlier run's log"
    assert sorted(p.name for p in out.iterdir()) == ["data"]


def test_a_run_from_pixels_is_refused_on_a_deployment_it_cannot_read(tmp_path: Path) -> None:
    class Elsewhere:
        """A deployment whose services' files are not on this machine (all a refusal reads)."""

        description = "a cluster"
        local_data_dir = None
        emulated_links = None
        fixed_size = False

    out = tmp_path / "run"
    with pytest.raises(ConfigError, match="from pixels reads the detectors' constellations"):
        main(settings(out, pixels=PixelSettings(from_pixels=True)), Elsewhere())  # type: ignore[arg-type]
    assert not out.exists()


def test_a_render_the_disk_cannot_hold_is_refused_before_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from swarmrec.experiments.places import pixels

    real = pixels.shutil.disk_usage(tmp_path)
    monkeypatch.setattr(pixels.shutil, "disk_usage", lambda p: real._replace(free=100_000_000))

    with pytest.raises(ConfigError, match=r"rendering 600 frames .* needs about 0.5 GB and 0.1 GB are free"):
        pixels._check_room(tmp_path / "run" / "rgbd", 600, say=False)
    pixels._check_room(tmp_path / "run" / "rgbd", 100, say=False)  # 80 MB: room enough
    assert not (tmp_path / "run").exists()
