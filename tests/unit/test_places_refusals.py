"""Settings a places run cannot honour are refused before it writes anything.

A user who typed a link setting the run cannot emulate gets one error, and neither a
half-written run folder nor the loss of an earlier run's stores."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmrec.deployments.links import LinkSpec
from swarmrec.errors import ConfigError, MalformedLineError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main


def settings(out: Path, **changes: object) -> PlacesSettings:
    base = PlacesSettings(source=DatasetSource(frames=40), robots=2, out=out, progress=False, plots=False)
    return base.with_(**changes)


def test_links_with_several_robots_a_process_leave_no_folder(tmp_path: Path) -> None:
    out = tmp_path / "run"
    refused = settings(out, hosting="robots:2", link=LinkSpec(rate_kbps=50))

    with pytest.raises(ConfigError, match="emulated links are per robot"):
        main(refused)

    assert not out.exists()


def test_a_bad_schedule_leaves_an_earlier_runs_stores_as_they_were(tmp_path: Path) -> None:
    out = tmp_path / "run"
    earlier = out / "data" / "robot0" / "index-shard" / "store.log"
    earlier.parent.mkdir(parents=True)
    earlier.write_bytes(b"an earlier run's records")
    schedule = tmp_path / "schedule.csv"
    schedule.write_text("start,end,robot\n5,ten,1\n")

    with pytest.raises(MalformedLineError, match=r"schedule\.csv"):
        main(settings(out, hosting="robot", schedule=schedule))

    assert earlier.read_bytes() == b"an earlier run's records"
    assert not (out / "dataset").exists()


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
