"""What the pods' probes cost the node: the services' own HTTP pages against exec'ing Python.

    sudo .venv/bin/python bench/bench_k8s_probes.py --out bench/results/k8s_probes.json

The same idle swarm (3 robots: 12 robot pods, the router and the gateway, all Ready, nothing
replayed) is deployed twice on the project's cluster (deploy/k8s/), with the same probe periods
(startup 2 s, readiness 5 s, liveness 10 s):

* ``http``: the manifests as they are, ``httpGet`` on ``/ready`` and ``/healthz`` (the runner's
  pages beside ``/metrics``, swarmrec/runtime/metrics.py);
* ``exec``: every probe replaced by the image's health check, ``python -m swarmrec.healthcheck``
  (what the manifests ran before), which reads the service's ``/metrics`` and looks for
  ``swarmrec_service_ready 1``.

For each, after the pods are Ready and a settling pause, the CPU time spent over a window is
read from the kernel's own accounting, not sampled: the ``kubepods`` cgroup (every container,
and the probe processes exec'd into them), plus the kubelet, containerd and the containerd shims
(an exec probe is a CRI ExecSync: containerd asks the pod's shim to run runc exec). The rest of
the machine (other jobs sharing its two cores) is not counted. The difference between the two
runs is what the exec probes cost, and per probe, divided by the probes run in the window.

Needs root and a running cluster with the images loaded (``make k8s-up``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, Kubectl, KubernetesDeployment, KubernetesSettings
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places.pipeline import prepare
from swarmrec.experiments.places.settings import PlacesSettings

REPO = Path(__file__).resolve().parents[1]
ROBOTS = 3
TICK = os.sysconf("SC_CLK_TCK")
KUBEPODS = Path("/sys/fs/cgroup/cpuacct/kubepods/cpuacct.usage")  # cgroup v1, the kubelet's cgroupfs driver
PERIODS = {"startupProbe": 2, "readinessProbe": 5, "livenessProbe": 10}
EXEC_PROBE = ["python", "-m", "swarmrec.healthcheck"]


def env_sh() -> dict[str, str]:
    import subprocess

    names = ["K8S_BIN", "KUBECONFIG_ADMIN"]
    script = f". {REPO / 'deploy/k8s/env.sh'}; " + "; ".join(f'echo "${n}"' for n in names)
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, check=True).stdout
    return dict(zip(names, out.splitlines(), strict=True))


def exec_overlay(folder: Path) -> Path:
    """The local overlay with every swarm service's probes exec'ing the image's health check."""
    probe = {"exec": {"command": EXEC_PROBE}}
    container = {
        "startupProbe": {**probe, "httpGet": None, "periodSeconds": 2, "timeoutSeconds": 3},
        "readinessProbe": {**probe, "httpGet": None, "periodSeconds": 5, "timeoutSeconds": 3},
        "livenessProbe": {**probe, "httpGet": None, "periodSeconds": 10, "timeoutSeconds": 5},
    }

    def patch(kind: str, name: str) -> dict[str, Any]:
        return {
            "apiVersion": "apps/v1",
            "kind": kind,
            "metadata": {"name": "any"},
            "spec": {"template": {"spec": {"containers": [{"name": name, **container}]}}},
        }

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "robots.json").write_text(json.dumps(patch("StatefulSet", "service")))
    (folder / "router.json").write_text(json.dumps(patch("Deployment", "router")))
    (folder / "gateway.json").write_text(json.dumps(patch("Deployment", "gateway")))
    doc = {
        "apiVersion": "kustomize.config.k8s.io/v1beta1",
        "kind": "Kustomization",
        "resources": [os.path.relpath(DEFAULT_OVERLAY, folder)],
        "patches": [
            {
                "path": "robots.json",
                "target": {"kind": "StatefulSet", "labelSelector": "swarmrec.io/robot-service=true"},
            },
            {"path": "router.json", "target": {"kind": "Deployment", "name": "router"}},
            {"path": "gateway.json", "target": {"kind": "Deployment", "name": "gateway"}},
        ],
    }
    (folder / "kustomization.yaml").write_text(json.dumps(doc, indent=1))
    return folder


def cluster_daemons() -> list[int]:
    """The kubelet, and the cluster's own containerd and shims (not the docker engine's: their
    command lines name the cluster's state folder)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            comm = (entry / "comm").read_text().strip()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if comm == "kubelet" or (comm.startswith("containerd") and "swarmrec-k8s" in cmdline):
            out.append(int(entry.name))
    return out


def process_cpu_s(pids: list[int]) -> float:
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])  # utime, stime
    return total / TICK


def window(seconds: float) -> dict[str, float]:
    """CPU seconds spent in the pods' cgroup and by the kubelet, containerd and the shims."""
    daemons = cluster_daemons()
    pods0, daemons0, t0 = int(KUBEPODS.read_text()), process_cpu_s(daemons), time.monotonic()
    time.sleep(seconds)
    pods1, daemons1, t1 = int(KUBEPODS.read_text()), process_cpu_s(daemons), time.monotonic()
    wall = t1 - t0
    pods_s, daemons_s = (pods1 - pods0) / 1e9, daemons1 - daemons0
    return {
        "window_s": wall,
        "pods_cpu_s": pods_s,
        "kubelet_containerd_shims_cpu_s": daemons_s,
        "total_cpu_s": pods_s + daemons_s,
        "cores_used": (pods_s + daemons_s) / wall,
    }


def measure(
    mode: str, overlay: Path, kubectl: Kubectl, tmp: Path, settle_s: float, window_s: float
) -> dict[str, Any]:
    run = PlacesSettings(
        source=DatasetSource(frames=60), robots=ROBOTS, swarm=f"probes_{mode}", out=tmp / mode
    )
    spec = prepare(run, dataset_dir=tmp / mode / "dataset").spec
    settings = KubernetesSettings(
        namespace=f"swarmrec-probes-{mode}", out=tmp / mode / "k8s", overlay=overlay, kubectl=kubectl
    )
    deployment = KubernetesDeployment(settings)
    try:
        deployment.start(spec)
        deployment.wait_ready()
        time.sleep(settle_s)
        figures = window(window_s)
        pods = 2 + ROBOTS * len(spec.kinds)
        probes = pods * window_s * (1 / PERIODS["readinessProbe"] + 1 / PERIODS["livenessProbe"])
        return {
            "mode": mode,
            "swarm_pods": pods,
            "probes_in_window": round(probes),
            **figures,
            "deploy": deployment.timings,
        }
    finally:
        deployment.remove()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench/results/k8s_probes.json")
    ap.add_argument("--window", type=float, default=60.0, help="seconds measured (default 60)")
    ap.add_argument("--settle", type=float, default=20.0, help="seconds after Ready before measuring")
    ap.add_argument("--rounds", type=int, default=1, help="measure each mode this many times, alternating")
    args = ap.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("run as root: the cluster's cgroups and daemons are root's")
    env = env_sh()
    kubectl = Kubectl((f"{env['K8S_BIN']}/kubectl",), Path(env["KUBECONFIG_ADMIN"]))
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        exec_dir = exec_overlay(Path(tmp) / "exec-overlay")
        for _ in range(args.rounds):
            for mode, overlay in (("http", DEFAULT_OVERLAY), ("exec", exec_dir)):
                runs.append(measure(mode, overlay, kubectl, Path(tmp), args.settle, args.window))
                print(json.dumps(runs[-1]), flush=True)

    def mean(mode: str, key: str) -> float:
        values = [r[key] for r in runs if r["mode"] == mode]
        return sum(values) / len(values)

    http, exe = mean("http", "cores_used"), mean("exec", "cores_used")
    probes_per_s = runs[0]["probes_in_window"] / args.window
    result = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_average": os.getloadavg()},
        "date": time.strftime("%Y-%m-%d"),
        "probe_periods_s": PERIODS,
        "runs": runs,
        "cores_used_http_probes": http,
        "cores_used_exec_probes": exe,
        "exec_minus_http_cores": exe - http,
        "probes_per_s": probes_per_s,
        "cpu_ms_per_exec_probe_more_than_http": (exe - http) / probes_per_s * 1000,
    }
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "runs"}, indent=2))


if __name__ == "__main__":
    main()
