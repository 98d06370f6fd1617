"""The main job against a swarm that already runs: containers, or robots.

``main_attached(folder, ...)`` reads the ``swarm.json`` that ``swarmrec
compose`` wrote in ``folder``, connects to the swarm's router from the host,
replays the dataset the detectors hold exactly as the local job does, reads
the services' counters from the swarm's Prometheus, and writes the same
report (docs/swarm.md). It starts and stops nothing.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.errors import ConfigError
from swarmrec.swarm.compose import read_swarm_file
from swarmrec.swarm.job import (
    SwarmSettings,
    as_on_the_wire,
    collect_loop_closures,
    prepare_dataset,
    replay_free,
    replay_lockstep,
)
from swarmrec.swarm.scrape import scrape_prometheus

__all__ = ["main_attached"]

ROBOT_KINDS = ("index-shard", "verifier", "descriptor", "detector")


def main_attached(
    folder: Path,
    *,
    out: Path,
    pace: str = "lockstep",
    plots: bool = True,
    progress: bool = True,
    check_offline: bool = True,
    wait_s: float = 120.0,
    on_step: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Replay through the running swarm described in ``folder``; write the report in ``out``."""
    from swarmrec.client import SwarmClient
    from swarmrec.swarm.report import write_report

    info = read_swarm_file(folder)
    if info.workload != "places":
        raise ConfigError(
            f"the swarm in {folder} runs the {info.workload} workload; "
            f"use `swarmrec landmarks --attach {folder}`"
        )
    settings = SwarmSettings(
        dataset=info.dataset,
        labels=Path(info.labels) if info.labels else None,
        groundtruth=Path(info.groundtruth) if info.groundtruth else None,
        robots=info.robots,
        preset=info.preset,
        pace=pace,
        out=out,
        swarm=info.swarm,
        request_timeout_s=info.request_timeout_s,
        plots=plots,
        progress=progress,
        check_offline=check_offline,
    )
    if settings.lockstep != info.lockstep:
        raise ConfigError(
            f"the swarm in {folder} was composed for {'lock-step' if info.lockstep else 'free'} replay; "
            f"--pace {pace} needs a swarm composed {'with' if settings.lockstep else 'without'} --lockstep"
        )
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    _source, _labels, seq, trajectory = prepare_dataset(settings)
    if seq.n_labels != info.n_labels:
        raise ConfigError(f"{info.dataset} has {seq.n_labels} labels, the swarm {info.n_labels}")
    wire_seq = as_on_the_wire(seq)
    bounds = np.asarray(info.label_bounds, np.int64)
    blocks = split_frames(len(seq), info.robots)
    timings: dict[str, float] = {"prepare_s": time.perf_counter() - t_start}
    with SwarmClient([info.router_endpoint], info.swarm, timeout_s=info.request_timeout_s) as client:
        t0 = time.perf_counter()
        client.wait_for({(k, r) for r in range(info.robots) for k in ROBOT_KINDS}, timeout_s=wait_s)
        timings["connect_s"] = time.perf_counter() - t0
        holding = {f"{m.kind}-{m.robot}": m.stored_items for m in client.members() if m.stored_items}
        if holding:
            # Frames of an earlier replay would be found as loop closures of this one.
            raise ConfigError(
                f"the swarm already holds data from an earlier run ({holding}); "
                "bring it down with its volumes (swarmrec compose down) and up again"
            )
        replay = (
            replay_lockstep(client, blocks, settings, on_step)
            if settings.lockstep
            else replay_free(client, blocks, settings)
        )
        timings["replay_s"] = replay.wall_s
        t0 = time.perf_counter()
        metrics = scrape_prometheus(info.prometheus_url, fresh_after=time.time())
        timings["scrape_s"] = time.perf_counter() - t0
        closures = collect_loop_closures(client, info.robots, replay)
    timings["total_s"] = time.perf_counter() - t_start
    return write_report(
        settings,
        seq=seq,
        wire_seq=wire_seq,
        trajectory=trajectory,
        preset=get_preset(info.preset),
        bounds=bounds,
        blocks=blocks,
        replay=replay,
        metrics=metrics,
        closures=closures,
        exit_codes={},
        timings=timings,
        deployment=f"attached: compose project {info.project}",
    )
