"""Container benchmark: building the images, starting a compose swarm, its memory.

    python bench/bench_compose.py --out bench/results/compose.json

Figures, each next to a baseline measured in the same run on the same machine:

* build: the local base images (debootstrap, ``--rebuild-base``), the
  wheelhouse, and the service and Prometheus images with no layer cache.
  Baseline: a ``pip install`` of the same wheels into a fresh virtual
  environment on the host, which is the work the service image's build repeats.
* cold start to healthy (every container's health check passes) for 4 and 10
  robots, from ``compose up`` with fresh volumes. Baseline: the same swarm as
  local processes (``LocalDeployment.start``, every process's ready line).
* memory: each container's memory after a lock-step replay of the synthetic
  world, by service kind (cgroup usage less the page cache, as ``docker
  stats`` shows it). Baseline: the resident set of the same service kinds run
  as local processes after the same replay.
* replay wall time through containers vs through local processes (4 robots).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
import venv
from collections import defaultdict
from pathlib import Path
from typing import Any

import docker

import swarmrec
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.compose import (
    ComposeDeployment,
    ComposeSettings,
    SwarmFile,
    down,
    up,
)
from swarmrec.deployments.local import LocalDeployment, free_port
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.experiments.places.keep import compose
from swarmrec.experiments.places.pipeline import prepare

REPO = Path(__file__).resolve().parents[1]


def _timed(cmd: list[str], **env: str) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=REPO, env={**os.environ, **env}, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def bench_build(rebuild_base: bool) -> dict[str, Any]:
    out: dict[str, Any] = {}
    subprocess.run([str(REPO / "deploy/engine.sh")], check=True, stdout=subprocess.DEVNULL)
    if rebuild_base:
        out["base_images_s"] = _timed([str(REPO / "deploy/base-image.sh"), "--force"])
    out["wheelhouse_s"] = _timed([str(REPO / "deploy/wheelhouse.sh")])
    version = swarmrec.__version__
    out["service_image_no_cache_s"] = _timed(
        [
            "docker", "build", "--quiet", "--no-cache", "--build-arg", "BASE_IMAGE=swarmrec-base:bookworm",
            "-t", f"swarmrec:{version}", "-f", "deploy/Dockerfile", "deploy",
        ]
    )  # fmt: skip
    out["prometheus_image_no_cache_s"] = _timed(
        [
            "docker", "build", "--quiet", "--no-cache",
            "--build-arg", "BASE_IMAGE=swarmrec-prometheus-base:bookworm",
            "-t", f"swarmrec-prometheus:{version}", "deploy/prometheus",
        ]
    )  # fmt: skip
    client = docker.from_env()
    out["service_image_mb"] = client.images.get(f"swarmrec:{version}").attrs["Size"] / 1e6
    out["prometheus_image_mb"] = client.images.get(f"swarmrec-prometheus:{version}").attrs["Size"] / 1e6
    out["base_image_mb"] = client.images.get("swarmrec-base:bookworm").attrs["Size"] / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        venv.create(tmp, with_pip=True)
        wheels = REPO / "deploy/.wheelhouse"
        out["baseline_host_pip_install_s"] = _timed(
            [f"{tmp}/bin/pip", "install", "--quiet", "--no-index", "--find-links", str(wheels), "swarmrec"]
        )
    out["ratio_service_image_over_host_install"] = (
        out["service_image_no_cache_s"] / out["baseline_host_pip_install_s"]
    )
    return out


def _container_memory_mb(client: docker.DockerClient, project: str) -> dict[str, dict[str, float]]:
    per_kind: dict[str, list[float]] = defaultdict(list)
    for c in client.containers.list(filters={"label": f"com.docker.compose.project={project}"}):
        stats = c.stats(stream=False)["memory_stats"]
        cache = stats.get("stats", {}).get("cache", stats.get("stats", {}).get("inactive_file", 0))
        per_kind[c.labels["org.swarmrec.service"]].append((stats["usage"] - cache) / 2**20)
    return {k: {"mean": sum(v) / len(v), "max": max(v), "n": len(v)} for k, v in sorted(per_kind.items())}


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _compose(robots: int, project: str, swarm: str, out: Path) -> tuple[SwarmFile, PlacesSettings]:
    """A places swarm of ``robots`` on the synthetic world, composed (not up) in ``out``."""
    run = PlacesSettings(robots=robots, swarm=swarm, out=out, progress=False, plots=False)
    settings = ComposeSettings(project=project, out=out, router_port=free_port(), prometheus_port=free_port())
    return compose(run, settings), run


def bench_cold_start(robots: int, tmp: Path) -> dict[str, Any]:
    project = f"swarmrec-bench-{robots}"
    info, run = _compose(robots, project, f"bench{robots}", tmp / f"compose{robots}")
    try:
        up_s = up(info, timeout_s=600)
    finally:
        down(info)
    local_run = run.with_(swarm=f"local{robots}", out=tmp / f"local{robots}")
    spec = prepare(local_run, dataset_dir=tmp / f"local{robots}" / "dataset").spec
    swarm = LocalDeployment(data_dir=tmp / f"data{robots}", log_dir=tmp / f"logs{robots}")
    t0 = time.perf_counter()
    try:
        swarm.start(spec, timeout_s=300)
        local_s = time.perf_counter() - t0
    finally:
        swarm.stop()
    return {
        "containers": 4 * robots + 2,
        "compose_up_to_healthy_s": up_s,
        "baseline_local_processes_to_ready_s": local_s,
        "ratio": up_s / local_s,
    }


def bench_replay_and_memory(tmp: Path, robots: int = 4) -> dict[str, Any]:
    project = "swarmrec-bench-mem"
    info, run = _compose(robots, project, "benchmem", tmp / "compose-mem")
    client = docker.from_env()
    try:
        up(info, timeout_s=600)
        deployment = ComposeDeployment(tmp / "compose-mem")
        summary = main(run.with_(out=tmp / "attached"), deployment).to_dict()
        containers = _container_memory_mb(client, project)
    finally:
        down(info)
    rss: dict[str, list[float]] = defaultdict(list)
    held: list[LocalDeployment] = []
    local_settings = PlacesSettings(
        robots=robots, out=tmp / "local", swarm="benchlocal", progress=False, plots=False
    )

    def hold(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    def on_step(t: int) -> None:
        # After the last step: every process's resident set, before the job stops them.
        if t == summary["dataset"]["frames"] // robots - 1:
            for sp in held[0].procs:
                rss[sp.kind].append(_rss_mb(sp.proc.pid))

    local = main(
        local_settings, LocalDeployment.for_run(local_settings.out), swarm_hook=hold, on_step=on_step
    ).to_dict()
    processes = {k: {"mean": sum(v) / len(v), "max": max(v), "n": len(v)} for k, v in sorted(rss.items())}
    return {
        "robots": robots,
        "frames": summary["dataset"]["frames"],
        "replay_containers_s": summary["timings"]["replay_s"],
        "baseline_replay_local_processes_s": local["timings"]["replay_s"],
        "ratio_replay": summary["timings"]["replay_s"] / local["timings"]["replay_s"],
        "identical_to_offline": summary["offline_check"]["identical"],
        "loop_closures_equal_local": summary["loop_closures"]["count"] == local["loop_closures"]["count"],
        "memory_mb_per_container": containers,
        "baseline_memory_mb_per_local_process": processes,
    }


def run(rebuild_base: bool) -> dict[str, Any]:
    result: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "date": time.strftime("%Y-%m-%d"),
    }
    print("build ...", flush=True)
    result["build"] = bench_build(rebuild_base)
    with tempfile.TemporaryDirectory() as tmp:
        for robots in (4, 10):
            print(f"cold start, {robots} robots ...", flush=True)
            result[f"cold_start_{robots}_robots"] = bench_cold_start(robots, Path(tmp))
        print("replay and memory, 4 robots ...", flush=True)
        result["replay_and_memory"] = bench_replay_and_memory(Path(tmp))
    return result


def cli() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=REPO / "bench/results/compose.json")
    p.add_argument("--rebuild-base", action="store_true", help="also time the debootstrap base images")
    args = p.parse_args()
    result = run(args.rebuild_base)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    cli()
