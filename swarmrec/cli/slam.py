"""``swarmrec slam``: multi-robot object-based SLAM: offline, live as services, merging a run's maps."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from swarmrec.cli.common import Subparsers
from swarmrec.cli.k8s import add_cluster_flags, kubectl_of
from swarmrec.slam.centralized import METHODS
from swarmrec.slam.dgs import DEFAULT_ETA, DEFAULT_LINEARISATIONS, MODES, DgsSettings
from swarmrec.slam.ordering import ORDERINGS
from swarmrec.slam.scenarios import WORLDS

if TYPE_CHECKING:
    from swarmrec.deployments.base import Deployment
    from swarmrec.deployments.local import LocalSettings
    from swarmrec.experiments.slam.report import LiveSlamSummary

__all__ = ["add", "run"]


def _solver_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("the distributed solver (docs/slam.md)")
    g.add_argument("--mode", choices=MODES, default="gauss-seidel", help="robots in turn or all at once")
    g.add_argument("--order", choices=ORDERINGS, default="flagged", help="Gauss-Seidel turn order")
    g.add_argument(
        "--gamma", type=float, help="over-relaxation in (0, 2) (default 1.9 for gauss-seidel, 1 for jacobi)"
    )
    g.add_argument(
        "--eta-rotation", type=float, default=DEFAULT_ETA, help="rotation stage's stopping threshold"
    )
    g.add_argument("--eta-pose", type=float, default=DEFAULT_ETA, help="pose stages' stopping threshold")
    g.add_argument("--max-iterations", type=int, default=1000, help="most iterations of one stage")
    g.add_argument(
        "--pose-linearisations",
        type=int,
        default=DEFAULT_LINEARISATIONS,
        help="pose stages (1: the paper's method; default 2: one relinearisation)",
    )
    g.add_argument(
        "--paper",
        action="store_true",
        help="the paper's method: plain Gauss-Seidel, one linearisation, eta 0.1 (overrides the above)",
    )
    g.add_argument("--centralized", choices=METHODS, default="gauss-newton", help="gtsam's reference method")


def _solver(args: argparse.Namespace) -> DgsSettings:
    """The solver's settings from its flags (``--paper``: the paper's method)."""
    if args.paper:
        return DgsSettings.paper()
    return DgsSettings(
        args.mode,
        args.order,
        args.gamma,
        args.eta_rotation,
        args.eta_pose,
        args.max_iterations,
        args.pose_linearisations,
    )


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "slam",
        help="multi-robot object-based SLAM: the distributed Gauss-Seidel offline, live as services, "
        "merging maps",
        description=(
            "The back end of object-based multi-robot SLAM (Choudhary et al.): each robot's pose graph "
            "(g2o), estimated by the distributed two-stage Gauss-Seidel, robots exchanging only the "
            "estimates of their separator variables. `solve` runs it in one process; `run` runs it as one "
            "slam service per robot over a real zenoh router; `merge` builds the robots' graphs from a "
            "finished `swarmrec run` (its verified loop closures) and merges their maps (docs/slam.md)."
        ),
    )
    verbs = p.add_subparsers(dest="slam_command", required=True, metavar="VERB")

    solve = verbs.add_parser(
        "solve",
        help="the distributed solve in one process, checked against gtsam",
        description=(
            "Read FOLDER's robot files (0.g2o, 1.g2o, ...), run the distributed two-stage Gauss-Seidel "
            "with one in-process agent per robot and gtsam's centralized solve, and write <r>.g2o, "
            "merged.g2o, centralized.g2o and summary.json to OUT."
        ),
    )
    solve.add_argument("folder", type=Path, help="robot folder, e.g. ../shared/data/dgs_blocks_world/4robots")
    solve.add_argument(
        "--out", type=Path, default=Path("runs/slam"), help="where to write (default runs/slam)"
    )
    solve.add_argument("--overwrite", action="store_true", help="replace an earlier result in OUT")
    _solver_flags(solve)
    solve.set_defaults(handler=run_solve)

    live = verbs.add_parser(
        "run",
        help="the distributed solve live: one slam service per robot over a zenoh router",
        description=(
            "Start a router and one slam service per robot (local processes, mutual TLS), each reading only "
            "its own g2o file; as the operator, load and start every robot, then watch while they take "
            "their turns and exchange separator estimates. Writes to OUT: iterations per stage, cost, "
            "ATE*/ARE* against gtsam's centralized Gauss-Newton, bytes per link per iteration measured "
            "against the 9/6-float model, the check that every message, report and estimate equals the "
            "in-process solve bit for bit, <r>.g2o, merged.g2o, centralized.g2o, map.png, summary.json. "
            "Without FOLDER, a simulated world (--world, --robots, --seed) is written to OUT/input first."
        ),
    )
    live.add_argument("folder", type=Path, nargs="?", help="robot folder (default: a simulated world)")
    live.add_argument("--world", choices=WORLDS, default="chairs", help="simulated world (default chairs)")
    live.add_argument("--robots", type=int, default=4, help="robots of the simulated world, 2-6 (default 4)")
    live.add_argument("--seed", type=int, default=0, help="seed of the simulated world (default 0)")
    live.add_argument("--out", type=Path, default=Path("runs/slam-live"), help="report folder")
    live.add_argument(
        "--peer-timeout-s",
        type=float,
        default=10.0,
        help="a robot silent this long is declared gone; the others end at the last consistent estimate",
    )
    live.add_argument(
        "--solve-timeout-s", type=float, default=600.0, help="the longest the whole solve may take"
    )
    live.add_argument("--insecure", action="store_true", help="plaintext links (debugging; logged)")
    live.add_argument(
        "--attach",
        type=Path,
        metavar="DIR",
        help="start nothing: solve through the team `swarmrec compose up --workload slam --out DIR` "
        "started (its robot folder or world, robots and swarm; the solver's flags still apply)",
    )
    live.add_argument(
        "--deployment",
        choices=("local", "k8s"),
        default="local",
        help="where the team runs: local processes (default), or k8s: one slam pod per robot in a new "
        "namespace of a Kubernetes cluster, mutual TLS from Secrets made for the run (docs/kubernetes.md)",
    )
    k8s = live.add_argument_group("kubernetes", "with --deployment k8s")
    k8s.add_argument(
        "--namespace", default="swarmrec-slam", help="the team's namespace (default swarmrec-slam)"
    )
    add_cluster_flags(k8s)
    live.add_argument("--no-check", action="store_true", help="skip the comparison with the in-process solve")
    live.add_argument("--overwrite", action="store_true", help="replace an earlier report in OUT")
    live.add_argument("--quiet", action="store_true", help="no progress")
    _solver_flags(live)
    live.set_defaults(handler=run_live)

    merge = verbs.add_parser(
        "merge",
        help="pixels -> constellations -> loop closures -> inter-robot constraints -> one merged map",
        description=(
            "Read a finished `swarmrec run` folder (its constellations, or detections from pixels, its "
            "loop_closures.csv and the synthetic world's camera poses): each robot's odometry chain "
            "(simulated from the world's poses with noise), and for every verified loop closure between "
            "two robots the relative pose of the two frames from their matched objects (the verifier's "
            "association, then RANSAC rigid alignment); outlier rejection (PCM, then GNC); then the "
            "distributed solve, live as slam services (default) or in one process (--offline). Reports "
            "the merged map's error against the world's ground truth."
        ),
    )
    merge.add_argument(
        "--run", type=Path, required=True, metavar="RUN_DIR", help="a finished `swarmrec run` folder"
    )
    merge.add_argument("--out", type=Path, default=Path("runs/slam-merge"), help="report folder")
    merge.add_argument(
        "--keyframe-every", type=int, default=5, help="a pose every K frames of a robot (default 5)"
    )
    merge.add_argument(
        "--odometry-sigma-deg", type=float, default=0.5, help="odometry rotation noise, degrees"
    )
    merge.add_argument(
        "--odometry-sigma-m", type=float, default=0.02, help="odometry translation noise, metres"
    )
    merge.add_argument(
        "--ransac-threshold-m",
        type=float,
        default=0.15,
        help="a matched object pair is an inlier within this (m)",
    )
    merge.add_argument("--noise-seed", type=int, default=0, help="seed of the simulated odometry noise")
    merge.add_argument(
        "--reject",
        choices=("none", "pcm", "pcm+gnc"),
        default="pcm+gnc",
        help="rejecting wrong inter-robot constraints before the solve (default pcm+gnc)",
    )
    merge.add_argument("--offline", action="store_true", help="solve in one process instead of as services")
    merge.add_argument("--insecure", action="store_true", help="plaintext links (debugging; logged)")
    merge.add_argument("--overwrite", action="store_true", help="replace an earlier report in OUT")
    merge.add_argument("--quiet", action="store_true", help="no progress")
    _solver_flags(merge)
    merge.set_defaults(handler=run_merge)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    handler = {"solve": run_solve, "run": run_live, "merge": run_merge}[args.slam_command]
    return handler(args)


def run_solve(args: argparse.Namespace) -> int:
    from swarmrec.slam.offline import SlamSettings, main

    settings = SlamSettings(
        args.folder, args.out, solver=_solver(args), centralized=args.centralized, overwrite=args.overwrite
    )
    summary = main(settings)
    return 0 if summary.converged else 1


def _local(args: argparse.Namespace) -> LocalSettings:
    """Where a live team runs: local processes, mutual TLS unless --insecure."""
    from swarmrec.deployments.local import LocalSettings

    return LocalSettings(security="insecure" if args.insecure else "mtls")


def _live_deployment(args: argparse.Namespace, out: Path) -> Deployment:
    """Local processes, or (``--deployment k8s``) a namespace of the cluster, its files in ``out/k8s``."""
    from swarmrec.deployments.local import LocalDeployment

    if args.deployment == "local":
        return LocalDeployment.for_run(out, _local(args))
    from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, KubernetesDeployment, KubernetesSettings
    from swarmrec.errors import ConfigError

    if args.insecure:
        raise ConfigError("a Kubernetes team runs under mutual TLS: drop --insecure")
    return KubernetesDeployment(
        KubernetesSettings(
            namespace=args.namespace,
            out=out / "k8s",
            overlay=args.overlay or DEFAULT_OVERLAY,
            kubectl=kubectl_of(args),
            max_robots=args.max_robots,
        )
    )


def run_live(args: argparse.Namespace) -> int:
    from swarmrec.experiments.slam import LiveSlamSettings, format_summary, main

    solve = {
        "out": args.out,
        "centralized": args.centralized,
        "solve_timeout_s": args.solve_timeout_s,
        "check": not args.no_check,
        "progress": not args.quiet,
        "overwrite": args.overwrite,
        "solver": _solver(args),
    }
    if args.attach is not None:
        summary = _solve_attached(args, solve)
    else:
        settings = LiveSlamSettings(
            folder=args.folder,
            world=args.world,
            robots=args.robots,
            seed=args.seed,
            peer_timeout_s=args.peer_timeout_s,
            **solve,
        )
        summary = main(settings, _live_deployment(args, settings.out))
    print(format_summary(summary))
    print(f"  report: {args.out / 'summary.json'}")
    identical = summary.check is None or summary.check.identical
    return 0 if summary.outcome == "converged" and identical else 1


def _solve_attached(args: argparse.Namespace, solve: dict[str, Any]) -> LiveSlamSummary:
    """A solve through the running team ``--attach`` names (a compose swarm's)."""
    from swarmrec.deployments.attach import attach
    from swarmrec.errors import ConfigError
    from swarmrec.experiments.slam import main
    from swarmrec.experiments.slam.keep import from_record

    if args.folder is not None or args.insecure:
        raise ConfigError(
            "--attach solves the running team's own problem, as it runs: drop FOLDER, --insecure"
        )
    deployment, info = attach(args.attach)
    if info.workload != "slam":
        raise ConfigError(f"{args.attach / 'swarm.json'} is a {info.workload} swarm, not a slam team")
    return main(from_record(info.experiment, **solve), deployment)


def run_merge(args: argparse.Namespace) -> int:
    from swarmrec.deployments.local import LocalDeployment
    from swarmrec.experiments.slam.merge import MergeSettings, format_merge, merge_run

    settings = MergeSettings(
        run=args.run,
        out=args.out,
        keyframe_every=args.keyframe_every,
        odometry_sigma_deg=args.odometry_sigma_deg,
        odometry_sigma_m=args.odometry_sigma_m,
        noise_seed=args.noise_seed,
        ransac_threshold_m=args.ransac_threshold_m,
        reject=args.reject,
        live=not args.offline,
        centralized=args.centralized,
        progress=not args.quiet,
        overwrite=args.overwrite,
        solver=_solver(args),
    )
    local = _local(args)
    summary = merge_run(settings, lambda folder: LocalDeployment.for_run(folder, local))
    print(format_merge(summary))
    print(f"  report: {args.out / 'summary.json'}")
    return 0 if summary.solved else 1
