"""Emulated links (Toxiproxy, built from its Go module): a robot out of range for some
lock-step steps misses exactly those, loses nothing it stored before, and is back in
the swarm when its link returns; every robot's traffic crosses its own shaped link."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmrec.cli.run import print_summary
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.links import LinkSpec, read_schedule
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.errors import MalformedLineError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main

ROBOTS, FRAMES, OUT, BACK, LOST_ROBOT = 3, 150, 5, 10, 1


@pytest.mark.slow
def test_a_robot_out_of_range_misses_its_steps_keeps_its_data_and_comes_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    schedule = tmp_path / "schedule.csv"
    schedule.write_text(f"# robot {LOST_ROBOT} out of range\nstart,end,robot\n{OUT},{BACK},{LOST_ROBOT}\n")
    stored: dict[str, dict[str, int]] = {}
    held: list[LocalDeployment] = []

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment) and d.links is not None
        held.append(d)

    def on_step(t: int) -> None:
        if t in (OUT - 1, BACK):
            with held[0].client(5.0) as client:
                stored[f"after step {t}"] = {f"{m.kind}-{m.robot}": m.stored_items for m in client.members()}

    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=tmp_path / "run",
        swarm="links",
        progress=False,
        plots=False,
    )
    # The links are the local deployment's: one proxy a robot, so one process a robot.
    local = LocalSettings(hosting="robot", link=LinkSpec(rate_kbps=50, latency_ms=5), schedule=schedule)
    summary = main(settings, LocalDeployment.for_run(settings.out, local), swarm_hook=hook, on_step=on_step)

    assert summary.links is not None
    assert summary.links.events == [
        (float(OUT), f"robot {LOST_ROBOT} out of range"),
        (float(BACK), f"robot {LOST_ROBOT} back in range"),
    ]
    assert summary.queries.missing_by_robot == {str(LOST_ROBOT): BACK - OUT}
    capsys.readouterr()
    print_summary(summary, settings.out)
    printed = capsys.readouterr().out
    assert f"    at step {OUT}: robot {LOST_ROBOT} out of range\n" in printed
    assert f"not compared ({BACK - OUT} answer slots missing)" in printed
    assert f"missing answers: {BACK - OUT} (robot {LOST_ROBOT}: {BACK - OUT})" in printed
    # What it stored before going out of range is all there when it comes back, and it stores again.
    before, after = stored[f"after step {OUT - 1}"], stored[f"after step {BACK}"]
    assert before[f"verifier-{LOST_ROBOT}"] == OUT
    assert after[f"verifier-{LOST_ROBOT}"] == OUT + 1
    # The other robots kept going, and every robot's own frames are in its verifier at the end.
    per = FRAMES // ROBOTS
    assert after["verifier-0"] == after["verifier-2"] == BACK + 1
    assert summary.queries.frames_replayed == ROBOTS * per - (BACK - OUT)


def test_a_schedule_with_a_bad_row_names_the_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "s.csv"
    path.write_text("start,end,robot\n0,5,1\n7,3,2\n")
    with pytest.raises(MalformedLineError, match=r"s\.csv:3: need 0 <= start < end"):
        read_schedule(path)


def test_a_schedule_says_who_is_out_of_range_when() -> None:
    from swarmrec.deployments.links import Outage, Schedule

    s = Schedule((Outage(2, 5, 1), Outage(4, 6, 2, LinkSpec(rate_kbps=1.0))), "step")
    assert s.state_at(1) == {}
    assert s.state_at(4) == {1: None, 2: LinkSpec(rate_kbps=1.0)}
    assert s.state_at(5) == {2: LinkSpec(rate_kbps=1.0)}
    assert s.changes() == [2, 4, 5, 6]


def test_the_ports_a_process_listens_on_are_read_from_the_kernel() -> None:
    import os
    import socket

    from swarmrec.deployments.links import listening_ports

    with socket.socket() as listening, socket.socket() as bound_only:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        bound_only.bind(("127.0.0.1", 0))
        ports = listening_ports(os.getpid())
        assert listening.getsockname()[1] in ports
        assert bound_only.getsockname()[1] not in ports  # bound, not listening
    assert listening_ports(2**22 + 1) == set()  # no such process
