"""The live view of the full-image method and of SLAM, in a real browser, as users run them.

* ``swarmrec run --method dvpr`` (the pipeline, real processes over mutual TLS): while
  the swarm is up after its replay, the page (headless Chromium) shows the place owners'
  loop closures (its count is theirs, each row one they hold), the load on each cluster
  owner as the run's summary counts it, the place-query funnel (every frame queried and
  answered, the closures), the cluster table's version, and only the panels of the
  method that runs.
* ``swarmrec landmarks`` (a small street): when every round has ended, the page counts
  every fusion update the robots made (one per view a robot folded in) and each row it
  shows is a decision a robot reached in the run.
* ``swarmrec slam run`` on a simulated world: when the team's solve has ended, the page
  shows every robot done, draws each robot's whole trajectory (one point per pose of its
  robot file) and marks the separators: for each pair of robots, as many rings as the
  robot has vertices on inter-robot edges with the other, counted here from the robot
  files alone.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import matplotlib.image as mpimg
import numpy as np
import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, parse_law, run_simulation
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.slam.pipeline import TERMINAL
from swarmrec.experiments.slam.pipeline import main as slam_main
from swarmrec.experiments.slam.settings import LiveSlamSettings
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings
from swarmrec.experiments.vpr import main as vpr_main
from swarmrec.runtime import keys
from swarmrec.services.live_view_slam import MAX_SEPARATORS
from swarmrec.slam.g2o import read_robot_folder
from swarmrec.slam.keys import symbol_chr
from swarmrec.wire import messages as pb
from tests.integration.browser import Browser, chromium_path


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Browser]:
    with Browser(chromium_path(), tmp_path_factory.mktemp("chromium") / "profile") as b:
        yield b


def rendered(png: bytes, path: Path) -> None:
    """A rendered page, not a blank one: the dark header, white panels, and contrast (kept
    at ``path`` for a person to look at)."""
    path.write_bytes(png)
    pixels = mpimg.imread(io.BytesIO(png), format="png")
    grey = pixels[..., :3].mean(axis=2)
    assert grey[:30].mean() < 0.3 and grey[100:].mean() > 0.7 and np.std(grey) > 0.1


VISIBLE = "[...document.querySelectorAll('[data-method]')].filter(e => !e.hidden).map(e => e.dataset.method)"


def bar_values(box: str, attr: str) -> str:
    return (
        f"Object.fromEntries([...document.querySelectorAll('#{box} [data-{attr}]')]"
        f".map(r => [r.dataset.{attr}, Number(r.querySelector('.value').textContent)]))"
    )


@pytest.mark.slow
def test_the_page_shows_a_dvpr_swarms_owners_funnel_and_closures(tmp_path: Path, browser: Browser) -> None:
    robots, frames = 3, 60
    seen: dict[str, Any] = {}

    def opened(deployment: Deployment) -> None:
        url = getattr(deployment, "live_view_url", "")
        assert url, "a dvpr swarm serves the live view"
        browser.open(url)
        browser.wait_for("document.querySelectorAll('[data-member]').length", lambda n: n > 0, 30, "members")

    def replayed(deployment: Deployment) -> None:
        with deployment.client(5.0, role="client") as client:
            held = {
                f"{c.query_robot_id}/{c.query_frame_index}/{c.match_robot_id}/{c.match_frame_index}"
                for r in range(robots)
                for c in client.call(
                    keys.endpoint(client.swarm, "place-owner", r, "loop_closures"),
                    pb.LoopClosuresRequest(),
                    pb.LoopClosureList,
                    target_robot=r,
                ).loop_closures
            }
        seen["held"] = held
        seen["count"] = browser.wait_for(
            "Number(document.getElementById('n-closures').textContent)",
            lambda n: n == len(held),
            30,
            "closures",
        )
        seen["rows"] = browser.evaluate(
            "[...document.querySelectorAll('[data-closure]')].map(r => r.dataset.closure)"
        )
        seen["funnel"] = browser.wait_for(
            bar_values("place-funnel", "stage"), lambda f: f.get("place queries") == frames, 30, "the funnel"
        )
        seen["owners"] = browser.wait_for(
            bar_values("owners", "owner"), lambda o: sum(o.values()) == frames, 30, "the owners' load"
        )
        seen["table"] = browser.evaluate("document.getElementById('tables').textContent")
        seen["visible"] = browser.evaluate(VISIBLE)
        seen["png"] = browser.screenshot()

    settings = VprRunSettings(
        run=PlacesSettings(
            source=DatasetSource(frames=frames),
            robots=robots,
            out=tmp_path / "run",
            progress=False,
            plots=False,
            pixels=PixelSettings(from_pixels=True),
        ),
        dvpr=DvprSettings(clusters_per_robot=5),
    )
    summary = vpr_main(settings, LocalDeployment.for_run, swarm_hook=opened, replayed_hook=replayed)
    assert isinstance(summary, DvprSummary)
    assert summary.queries.frames == frames and summary.queries.missing_slots == 0

    held = seen["held"]
    assert held, "the office's frames close loops"
    assert seen["count"] == len(held)
    assert set(seen["rows"]) <= held and len(seen["rows"]) == min(len(held), 50)
    f = seen["funnel"]
    assert f["place queries"] == f["owner answered"] == frames
    assert f["closures"] == len(held) and f["verified"] >= f["closures"] and f["matched"] >= f["verified"]
    # Each owner's load as the run's summary counts it (its metrics at the end of the replay).
    assert seen["owners"] == {f"owner {r}": q for r, q in enumerate(summary.load.queries)}
    assert seen["table"].startswith("v")  # the cluster table's version, as the owners have it
    assert (
        "dvpr" in seen["visible"]
        and "constellations" not in seen["visible"]
        and "slam" not in seen["visible"]
    )
    rendered(seen["png"], tmp_path / "live-view-dvpr.png")


@pytest.mark.slow
def test_the_page_counts_a_landmark_swarms_fusion_updates(tmp_path: Path, browser: Browser) -> None:
    robots, configurations = 4, 3
    seen: dict[str, Any] = {}

    def up(deployment: Deployment) -> None:
        seen["url"] = getattr(deployment, "live_view_url", "")

    def progressed(done: int, total: int) -> None:
        if done < total:
            return
        browser.open(seen["url"])
        seen["count"] = browser.wait_for(
            "Number(document.getElementById('n-fusion').textContent)", lambda n: n > 0, 30, "updates"
        )
        seen["rows"] = browser.evaluate(
            "[...document.querySelectorAll('[data-fusion]')].map(r => r.dataset.fusion)"
        )
        seen["visible"] = browser.evaluate(VISIBLE)
        seen["png"] = browser.screenshot()

    settings = LandmarkSettings(
        out=tmp_path / "run",
        configurations=configurations,
        robots=robots,
        laws=(parse_law("paper:0"),),
        progress=False,
    )
    result = run_simulation(
        settings, LocalDeployment.for_run(settings.out), on_round=progressed, swarm_hook=up
    )
    assert result.errors == [] and result.failures == {}
    assert seen.get("url"), "a landmark swarm serves the live view"
    # One update per view a robot folded in, every one heard by the gateway.
    assert seen["count"] == sum(r.incorporated for r in result.rounds) > 0
    decided = {(r.robot, d) for r in result.rounds for d in r.decisions[1:]}
    final = {(r.robot, r.decisions[-1]) for r in result.rounds}
    assert 0 < len(seen["rows"]) <= 10
    for row in seen["rows"]:
        robot, _round, decision, heard_all = (int(x) for x in row.split("/"))
        assert (robot, decision) in (final if heard_all else decided), row
    assert "landmarks" in seen["visible"] and "closures" not in seen["visible"]
    rendered(seen["png"], tmp_path / "live-view-landmarks.png")


def separators_of(folder: Path) -> dict[str, int]:
    """For each ordered pair of robots "a-b": how many of robot a's vertices are on an edge
    with one of robot b's, from the robot files."""
    graph = read_robot_folder(folder).graph
    shared: dict[str, set[int]] = {}
    for edge in graph.edges:
        a, b = graph.robot_of(edge.source), graph.robot_of(edge.target)
        if a != b:
            shared.setdefault(f"{a}-{b}", set()).add(edge.source)
            shared.setdefault(f"{b}-{a}", set()).add(edge.target)
    return {pair: len(ks) for pair, ks in shared.items()}


def poses_of(folder: Path) -> dict[str, int]:
    graph = read_robot_folder(folder).graph
    return {str(r): sum(symbol_chr(k).islower() for k in graph.robot_keys(r)) for r in graph.robots}


def test_the_page_draws_a_slam_teams_trajectories_and_separators(tmp_path: Path, browser: Browser) -> None:
    out = tmp_path / "slam"
    seen: dict[str, Any] = {}

    def up(deployment: Deployment) -> None:
        seen["url"] = getattr(deployment, "live_view_url", "")

    def ended(statuses: dict[int, pb.SlamStatus | None]) -> None:
        if "png" in seen or not all(s is not None and s.state in TERMINAL for s in statuses.values()):
            return
        browser.open(seen["url"])
        seen["states"] = browser.wait_for(
            "[...document.querySelectorAll('[data-slam]')].map(r => r.dataset.state)",
            lambda s: s == ["done"] * 3,
            30,
            "the team's states",
        )
        seen["points"] = browser.wait_for(
            "Object.fromEntries([...document.querySelectorAll('[data-trajectory]')]"
            ".map(l => [l.dataset.trajectory, l.getAttribute('points').trim().split(/ +/).length]))",
            lambda p: len(p) == 3,
            30,
            "the trajectories",
        )
        seen["separators"] = browser.wait_for(
            "(() => { const c = {}; for (const r of document.querySelectorAll('[data-separator]'))"
            " c[r.dataset.separator] = (c[r.dataset.separator] || 0) + 1; return c; })()",
            lambda c: len(c) > 0,
            30,
            "the separators",
        )
        seen["visible"] = browser.evaluate(VISIBLE)
        seen["png"] = browser.screenshot()

    settings = LiveSlamSettings(out=out, world="house", robots=3, seed=1, progress=False, plots=False)
    summary = slam_main(settings, LocalDeployment.for_run(out), on_status=ended, swarm_hook=up)
    assert summary.outcome == "converged"
    assert seen.get("url"), "a slam team serves the live view"

    assert seen["states"] == ["done"] * 3
    # Every pose of each robot's file is a point of its line (none thinned at this size).
    assert seen["points"] == poses_of(out / "input")
    expected = separators_of(out / "input")
    assert max(expected.values()) <= MAX_SEPARATORS  # so no robot's rings are cut
    assert seen["separators"] == expected
    assert "slam" in seen["visible"] and "constellations" not in seen["visible"]
    rendered(seen["png"], tmp_path / "live-view-slam.png")
