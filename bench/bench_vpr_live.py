"""Live re-balancing of cluster owners, measured on the offline evaluation's office.

    python bench/bench_vpr_live.py --out bench/results/vpr_live.json --plot docs/figures/vpr_live.png

The deployment office of ``swarmrec vpr evaluate`` (office 15000, its 2,500 frames, held out
from the model's and the centres' training) is rendered and described once, cut among 20
robots, and replayed in lock-step through a live swarm (a router, and per robot a verifier
and a place-owner in one process, real zenoh) that starts from the paper's random
assignment of 8 clusters per robot (the shipped k = 160 centres) and is re-balanced live
after every 6 steps (120 queries, about the offline rule's 5 % periods). Measured in the
same run, on the same descriptors:

* the live swarm: worst balance over the run and after its first table, relative AUC
  against the centralized search (both on the descriptors as owners store them, int8
  decoded), bytes between robots a query as the services counted them, by message (moves
  and copies included), the tables' sizes and how long each re-balancing took;
* the offline simulation of the *same table sequence*: every frame's owner, match and
  distance compared with the live swarm's (0 differences expected);
* the paper's static assignments offline on the same descriptors: one cluster per robot
  (k = 20) and 8 clusters per robot (k = 160), never re-balanced.

The figure: the busiest robot's share over the mission (per 120-query period) for the
three, and the bytes a query by message for the live swarm.
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

import numpy as np

from swarmrec.core.split import split_frames
from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.vpr.report import as_stored, live_answers, offline_answers
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.runtime import keys
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.settings import PlaceSettings, VprSettings
from swarmrec.vpr.clusters import Router, load_centres, random_assignment
from swarmrec.vpr.data import render_world
from swarmrec.vpr.evaluation import EvaluationSettings, make_team, team_auc
from swarmrec.vpr.model import DescriptorModel
from swarmrec.vpr.places import PlaceThresholds, same_place
from swarmrec.vpr.simulation import Answers, arrival_order, bytes_per_query, run_queries
from swarmrec.wire import messages as pb

REPO = Path(__file__).resolve().parents[1]
ROBOTS, C, EVERY_STEPS = 20, 8, 6
PERIOD = ROBOTS * EVERY_STEPS
FLOAT32 = pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32


def deployment_descriptors(frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The evaluation's deployment office: its descriptors and same-place matrix."""
    s = EvaluationSettings(out=Path("unused"))
    world = render_world(s.deployment_seed, frames, 1, vary=False, offset=False)
    x = DescriptorModel(None, intra_op_threads=2).describe(world.images)
    same = same_place(
        world.positions, world.directions, world.frames, PlaceThresholds(s.max_distance_m, s.max_angle_deg, 0)
    )
    return x.astype(np.float32), same


def live_run(
    x: np.ndarray, work: Path
) -> tuple[dict[tuple[int, int], pb.PlaceReport], list[tuple[int, pb.ClusterTable]], dict[str, Any]]:
    """Replay ``x`` in lock-step through the live swarm, re-balancing every EVERY_STEPS steps."""
    blocks = split_frames(len(x), ROBOTS)
    spec = SwarmSpec(
        BusSettings(swarm="vprlive", n_robots=ROBOTS, request_timeout_s=10.0),
        ("verifier", "place-owner"),
        (PlaceSettings(), VprSettings(vpr_clusters_per_robot=C)),
        swarm_kinds=(),
    )
    deployment = LocalDeployment(
        data_dir=work / "data", log_dir=work / "logs", hosting="robot", security="insecure"
    )
    reports: dict[tuple[int, int], pb.PlaceReport] = {}
    tables: list[tuple[int, pb.ClusterTable]] = []
    rebalance_s: list[float] = []
    replies: list[pb.RebalanceReply] = []
    try:
        deployment.start(spec, timeout_s=180.0)
        deployment.wait_ready(180.0)
        with deployment.client(30.0) as client:
            sent = 0
            t0 = time.perf_counter()
            for t in range(max(len(b) for b in blocks)):
                for r, block in enumerate(blocks):
                    if t >= len(block):
                        continue
                    g = block.start + t
                    msg = pb.PlaceFrame(
                        robot_id=r,
                        frame_index=t,
                        frame_id=str(g),
                        descriptor=x[g].astype("<f4").tobytes(),
                        encoding=FLOAT32,
                        constellation=pb.Constellation(),
                    )
                    key = keys.endpoint("vprlive", "place-owner", r, "process")
                    reports[(r, t)] = client.call(key, msg, pb.PlaceReport, target_robot=None, timeout_s=30.0)
                    sent += 1
                if (t + 1) % EVERY_STEPS == 0 and t + 1 < len(blocks[0]):
                    ts = time.perf_counter()
                    key = keys.endpoint("vprlive", "place-owner", 0, "rebalance")
                    reply = client.call(
                        key, pb.RebalanceRequest(), pb.RebalanceReply, target_robot=None, timeout_s=300.0
                    )
                    rebalance_s.append(time.perf_counter() - ts)
                    tables.append((sent, reply.table))
                    replies.append(reply)
            replay_s = time.perf_counter() - t0
        metrics = deployment.metrics()
    finally:
        deployment.stop()
    by_message = metrics.by_label("swarmrec_message_bytes_sent_total", "message", scope="swarm")
    q = len(reports)
    facts = {
        "replay_s": replay_s,
        "rebalance_s": {"mean": float(np.mean(rebalance_s)), "max": float(np.max(rebalance_s))},
        "rebalances": len(tables),
        "moved_descriptors": int(sum(r.moved for r in replies)),
        "pending_after_rollouts": int(sum(r.pending for r in replies)),
        "clusters_last_table": len(tables[-1][1].owners),
        "bytes_per_query": sum(by_message.values()) / q,
        "bytes_per_query_by_message": {k: v / q for k, v in sorted(by_message.items())},
        "owner_failures": sum(1 for rep in reports.values() if not rep.answered),
    }
    return reports, tables, facts


def balance_by_period(owners_in_order: np.ndarray) -> list[float]:
    out = []
    for lo in range(0, len(owners_in_order), PERIOD):
        part = owners_in_order[lo : lo + PERIOD]
        counts = np.bincount(part, minlength=ROBOTS)
        out.append(float(counts.max() / counts.mean()))
    return out


def scored(
    name: str, answers: Answers, team: Any, centralized: float, order: np.ndarray, robots: np.ndarray
) -> dict[str, Any]:
    counts = np.bincount(answers.owners, minlength=ROBOTS)
    after = answers.owners[order[PERIOD:]]
    later = np.bincount(after, minlength=ROBOTS)
    auc = team_auc(team, answers)
    return {
        "name": name,
        "worst_balance_ratio": float(counts.max() / counts.mean()),
        "worst_balance_ratio_after_first_period": float(later.max() / later.mean()),
        "auc": auc,
        "relative_auc": auc / centralized,
        "model_bytes_per_query_int8": bytes_per_query(answers, robots, 132)["total"],
        "balance_by_period": balance_by_period(answers.owners[order]),
    }


def plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for run in result["runs"]:
        series = run["balance_by_period"]
        a.plot(
            np.arange(len(series)) * PERIOD,
            series,
            label=f"{run['name']} (run: {run['worst_balance_ratio']:.2f})",
        )
    a.axhline(1.5, color="grey", ls=":", lw=1)
    a.set_xlabel("queries (lock-step arrival order)")
    a.set_ylabel("busiest / mean, per 120-query period")
    a.set_title(f"{ROBOTS} robots, office {result['office']}")
    a.legend(fontsize=8)
    msgs = result["live"]["bytes_per_query_by_message"]
    names = sorted(msgs, key=lambda k: -msgs[k])
    b.barh(names, [msgs[k] for k in names])
    b.invert_yaxis()
    b.set_xlabel("bytes between robots a query (measured)")
    b.set_title(f"live re-balanced swarm: {result['live']['bytes_per_query']:.0f} B a query")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(out: Path, plot_path: Path | None, frames: int) -> dict[str, Any]:
    started = time.perf_counter()
    x, same = deployment_descriptors(frames)
    describe_s = time.perf_counter() - started
    blocks = split_frames(len(x), ROBOTS)
    robots = np.concatenate([np.full(len(b), r, np.int64) for r, b in enumerate(blocks)])
    order = arrival_order(robots)
    team = make_team(ROBOTS, same)
    assert np.array_equal(team.robots, robots), "the evaluation's cut is the swarm's"
    stored = as_stored(x, "int8")
    centralized = team_auc(team, run_queries(stored, robots, np.zeros(len(x), np.int64), order))
    with tempfile.TemporaryDirectory(prefix="vpr-live-") as tmp:
        reports, tables, facts = live_run(x, Path(tmp))
    live = live_answers(reports, blocks)
    start = Router(
        load_centres(shipped_model(DESCRIPTOR_CENTRES), ROBOTS * C), random_assignment(ROBOTS, C, 0)
    )
    replay = offline_answers(x, start, blocks, "int8", tables)
    differ = {
        "owners": int(np.count_nonzero(live.owners != replay.owners)),
        "matches": int(np.count_nonzero(live.matches != replay.matches)),
    }
    runs = [scored("live, re-balanced every 6 steps", live, team, centralized, order, robots)]
    for c in (1, C):
        router = Router(
            load_centres(shipped_model(DESCRIPTOR_CENTRES), ROBOTS * c), random_assignment(ROBOTS, c, 0)
        )
        static = run_queries(stored, robots, router.route_many(x)[1], order)
        runs.append(
            scored(
                f"paper, {c} cluster{'s' if c > 1 else ''} per robot",
                static,
                team,
                centralized,
                order,
                robots,
            )
        )
    result = {
        "what": "issue 26 part 3: live re-balancing of cluster owners on the evaluation's office",
        "office": EvaluationSettings(out=Path("unused")).deployment_seed,
        "frames": len(x),
        "robots": ROBOTS,
        "clusters_per_robot_start": C,
        "rebalance_every_steps": EVERY_STEPS,
        "centralized_auc": centralized,
        "live": facts,
        "offline_replay_of_the_same_tables_differs": differ,
        "runs": runs,
        "seconds": {"render_and_describe": describe_s, "total": time.perf_counter() - started},
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    if plot_path is not None:
        plot(result, plot_path)
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "vpr_live.json")
    parser.add_argument("--plot", type=Path, default=REPO / "docs" / "figures" / "vpr_live.png")
    parser.add_argument(
        "--frames", type=int, default=2500, help="frames of the office (the evaluation's 2,500)"
    )
    args = parser.parse_args()
    r = main(args.out, args.plot, args.frames)
    line = ", ".join(
        f"{run['name']}: balance {run['worst_balance_ratio']:.2f}, relative AUC {run['relative_auc']:.3f}"
        for run in r["runs"]
    )
    differs = r["offline_replay_of_the_same_tables_differs"]
    print(f"{line}; live {r['live']['bytes_per_query']:.0f} B a query; offline replay differs {differs}")
