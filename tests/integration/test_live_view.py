"""The live view in a real browser while a swarm replays.

A 3-robot swarm (router, gateway, and detector, descriptor, index-shard and verifier
per robot, real processes, mutual TLS) serves its live view from the gateway. Over
plain HTTP: no token, a wrong one, an unknown path and a sixth event stream are
refused, and the state lists the members the swarm lists. In headless Chromium
(Debian's, driven over the DevTools protocol): the page shows every member; during a
paced replay the loop closures arrive on it as the descriptors accept them (its count
is theirs, each row one they hold); a verifier that stops is shown as gone; and its
screenshot is a rendered page, not a blank one.
"""

from __future__ import annotations

import contextlib
import io
import json
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

from swarmrec.deployments.local import LocalDeployment
from swarmrec.services.live_view import MAX_CONNECTIONS
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.wire import messages as pb
from tests.integration.browser import Browser, chromium_path
from tests.integration.conftest import running_swarm
from tests.integration.support import write_office

ROBOTS, STEPS = 3, 60


@pytest.fixture(scope="module")
def swarm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalDeployment]:
    tmp = tmp_path_factory.mktemp("live")
    dataset = write_office(tmp / "dataset", n_frames=ROBOTS * STEPS)
    parts = (PlaceSettings(lockstep=True), DetectorSettings(dataset=str(dataset)))
    with running_swarm(tmp, "live-view", *parts, robots=ROBOTS) as deployment:
        yield deployment


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Browser]:
    with Browser(chromium_path(), tmp_path_factory.mktemp("chromium") / "profile") as b:
        yield b


def get(url: str, timeout: float = 10.0) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as reply:
            return reply.status, reply.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def api(swarm: LocalDeployment, path: str) -> str:
    base, token = swarm.live_view_url.split("/?token=")
    return f"{base}{path}?token={token}"


def test_without_the_token_nothing_is_served_and_the_state_lists_the_members(swarm: LocalDeployment) -> None:
    url = swarm.live_view_url
    base = url.split("/?")[0]

    assert url.startswith("http://127.0.0.1:") and "token=" in url
    assert get(base + "/")[0] == 403
    assert get(base + "/api/state?token=wrong")[0] == 403
    assert get(api(swarm, "/nothing"))[0] == 404
    status, page = get(url)
    assert status == 200 and b"<title>swarmrec live view</title>" in page
    state = json.loads(get(api(swarm, "/api/state"))[1])
    with swarm.client() as client:
        members = {(m.kind, m.robot) for m in client.members()}
    assert {(m["kind"], m["robot"]) for m in state["members"]} == members
    assert state["swarm"] == "live-view" and state["placement"]["version"] >= 0
    assert sorted(state["shard_load"]) == [str(r) for r in range(ROBOTS)]


def test_event_streams_are_bounded(swarm: LocalDeployment) -> None:
    opened = []
    try:
        for _ in range(4):  # web_max_streams' default
            reply = urllib.request.urlopen(api(swarm, "/api/events"), timeout=10)
            assert reply.status == 200 and reply.readline() == b": subscribed\n"
            opened.append(reply)
        assert get(api(swarm, "/api/events"))[0] == 503
    finally:
        for reply in opened:
            reply.close()
    # A closed stream frees its slot (noticed at its next write: the keepalive at the latest).
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            reply = urllib.request.urlopen(api(swarm, "/api/events"), timeout=5)
        except urllib.error.HTTPError as e:
            assert e.code == 503
            time.sleep(1)
            continue
        reply.close()
        return
    raise AssertionError("no stream slot came free after the readers left")


def test_connections_are_bounded_and_an_idle_flood_does_not_keep_the_page_away(
    swarm: LocalDeployment,
) -> None:
    host, port = swarm.live_view_url.split("//")[1].split("/")[0].split(":")
    flood = [socket.create_connection((host, int(port)), timeout=10) for _ in range(MAX_CONNECTIONS + 8)]
    try:
        closed = 0
        for s in flood:
            s.settimeout(0.5)
            with contextlib.suppress(TimeoutError):  # a timeout: served, its thread waits for a request
                closed += s.recv(1) == b""
        assert closed >= 8
    finally:
        for s in flood:
            s.close()
    deadline = time.monotonic() + 10
    while get(api(swarm, "/api/state"), timeout=5)[0] != 200:
        assert time.monotonic() < deadline, "the page stayed away after the flood left"
        time.sleep(0.2)


def test_the_page_shows_members_closures_as_they_arrive_and_a_member_that_left(
    swarm: LocalDeployment, browser: Browser, tmp_path: Path
) -> None:
    with swarm.client() as client:
        n_members = len(client.members())
    browser.open(swarm.live_view_url)
    browser.wait_for(
        "document.querySelectorAll('[data-member]').length", lambda n: n == n_members, 30, "members"
    )
    browser.wait_for("document.getElementById('swarm').textContent", lambda s: s == "live-view", 10, "name")

    # A paced replay while the page is open: closures come on its event stream.
    errors: list[str] = []

    def replay() -> None:
        with swarm.client() as c:
            for t in range(STEPS):
                replies = c.step(t, timeout_s=10)
                if not all(isinstance(r, pb.StepReply) for r in replies):
                    errors.append(f"step {t}: {replies}")
                time.sleep(0.05)

    player = threading.Thread(target=replay)
    player.start()
    player.join(timeout=300)
    assert not player.is_alive() and not errors, errors

    with swarm.client() as client:
        held = {
            f"{c.query_robot_id}/{c.query_frame_index}/{c.match_robot_id}/{c.match_frame_index}"
            for r in range(ROBOTS)
            for c in client.loop_closures(r)
        }
    assert held, "the office's first frames close loops"
    count = browser.wait_for(
        "Number(document.getElementById('n-closures').textContent)", lambda n: n == len(held), 30, "count"
    )
    assert count == len(held)
    rows = browser.evaluate("[...document.querySelectorAll('[data-closure]')].map(r => r.dataset.closure)")
    assert set(rows) <= held and len(rows) == min(len(held), 50)
    arrived = browser.evaluate("document.querySelectorAll('[data-closure].new').length")
    assert arrived > 0  # at least some came on the event stream, before any poll
    load = browser.evaluate("[...document.querySelectorAll('[data-shard]')].map(r => r.dataset.shard)")
    assert load == [f"shard {r}" for r in range(ROBOTS)]
    shown = browser.evaluate("[...document.querySelectorAll('[data-message]')].map(r => r.dataset.message)")
    assert "VerifyRequest" in shown and "PartialQuery" in shown

    png = browser.screenshot()
    (tmp_path / "live-view.png").write_bytes(png)
    pixels = mpimg.imread(io.BytesIO(png), format="png")
    assert pixels.shape[:2] == (1000, 1400)
    # Rendered: the dark header, white panels, blue bars, text (not one colour).
    grey = pixels[..., :3].mean(axis=2)
    assert grey[:30].mean() < 0.3 and grey[100:].mean() > 0.8 and np.std(grey) > 0.1

    # A member that stops is shown as gone, at once (its liveliness token went away).
    verifier = swarm.find("verifier", ROBOTS - 1)
    swarm.stop_process(verifier)
    browser.wait_for(
        f"document.querySelector('[data-member=\"verifier-{ROBOTS - 1}\"]')?.className",
        lambda c: c == "gone",
        30,
        "the stopped verifier",
    )
