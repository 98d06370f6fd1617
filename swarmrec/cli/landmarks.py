"""``swarmrec landmarks``: cooperative landmark recognition through a swarm (the WNBC paper's experiment)."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.cli.k8s import add_cluster_flags, kubectl_of
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.compose import ComposeDeployment
from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, KubernetesDeployment, KubernetesSettings
from swarmrec.deployments.local import LocalDeployment
from swarmrec.errors import ConfigError
from swarmrec.experiments.landmarks import DEFAULT_LAWS, VIEW_PRESETS, LandmarkSettings, main, parse_law

__all__ = ["add", "run"]


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "landmarks",
        help="cooperative landmark recognition: a simulated street, each robot's CNN, fusion over zenoh",
        description=(
            "Simulate a swarm in a street of 19 landmarks (the WNBC paper's experiment): each robot "
            "renders what it faces, its detector (classifier mode) classifies it, the fusion services "
            "flood the outputs to their radio neighbours over a real zenoh router and fuse them with "
            "the weighted naive Bayes classifier. Writes the recognition rate against incorporated "
            "messages per weight law (Fig. 3), two configurations (Fig. 4), the confusion matrix "
            "(Fig. 5), bytes per round and checks to OUT (docs/landmarks.md)."
        ),
    )
    p.add_argument("--configurations", type=int, default=118, help="street configurations (default 118)")
    p.add_argument("--robots", type=int, default=10, help="robots (default 10; with --attach, the swarm's)")
    p.add_argument(
        "--laws",
        default=",".join(law.key for law in DEFAULT_LAWS),
        help="weight laws to compare, comma-separated: paper:LAMBDA or agreement[:PRIOR_LAMBDA] "
        "(default: the paper's four lambdas and the adaptive law)",
    )
    p.add_argument(
        "--views",
        choices=sorted(VIEW_PRESETS),
        default="nominal",
        help="nominal: the nuisances the CNN was trained on; harsh: occluded, dark, noisy views "
        "(single robot near the paper's 68 %%) (default nominal)",
    )
    p.add_argument("--radio-range", type=float, default=7.0, help="talk below this distance (m, default 7)")
    p.add_argument("--seed", type=int, default=0, help="configurations and views (default 0)")
    p.add_argument("--model", default="", help="classifier ONNX (default: the shipped one)")
    p.add_argument("--figure-law", help="law of Figs. 4 and 5 (default paper:2 when run)")
    p.add_argument(
        "--attach",
        type=Path,
        metavar="DIR",
        help="run the rounds through the compose swarm of DIR (swarmrec compose up --workload landmarks) "
        "instead of starting local processes",
    )
    p.add_argument(
        "--deployment",
        choices=("local", "k8s"),
        default="local",
        help="where the robots run when not attached: local processes (default), or k8s: a detector and a "
        "fusion pod per robot in a new namespace of a Kubernetes cluster (docs/kubernetes.md)",
    )
    k8s = p.add_argument_group("kubernetes", "with --deployment k8s")
    k8s.add_argument(
        "--namespace", default="swarmrec-landmarks", help="the swarm's namespace (default swarmrec-landmarks)"
    )
    add_cluster_flags(k8s)
    p.add_argument("--out", type=Path, default=Path("runs/landmarks"), help="report folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    laws = tuple(parse_law(text) for text in args.laws.split(",") if text.strip())
    if args.figure_law and args.figure_law not in {law.key for law in laws}:
        raise ConfigError(f"--figure-law {args.figure_law} is not one of --laws ({args.laws})")
    attached = ComposeDeployment(args.attach) if args.attach is not None else None
    fixed: dict[str, object] = {}
    if attached is not None:
        record = attached.info.experiment
        fixed = {"robots": attached.info.robots, "swarm": attached.info.swarm}
        if "request_timeout_s" in record:
            fixed["request_timeout_s"] = max(10.0, float(record["request_timeout_s"]))
    settings = LandmarkSettings(
        out=args.out,
        configurations=args.configurations,
        robots=args.robots,
        seed=args.seed,
        laws=laws,
        views=args.views,
        radio_range=args.radio_range,
        model=args.model,
        progress=not args.quiet,
    )
    if fixed:
        settings = settings.with_(**fixed)
    deployment: Deployment
    if attached is not None:
        deployment = attached
    elif args.deployment == "k8s":
        deployment = KubernetesDeployment(
            KubernetesSettings(
                namespace=args.namespace,
                out=settings.out / "k8s",
                overlay=args.overlay or DEFAULT_OVERLAY,
                kubectl=kubectl_of(args),
                max_robots=args.max_robots,
            )
        )
    else:
        deployment = LocalDeployment.for_run(settings.out)
    summary = main(settings, deployment, figure_law=args.figure_law)
    st, checks = summary.settings, summary.checks
    print(
        f"{st.configurations} configurations x {st.robots} robots, {st.views} views: "
        f"{checks.robot_rounds} of {checks.expected_robot_rounds} robot-rounds recorded"
    )
    print(f"correct recognition (%) after k incorporated messages, k = 0 .. {st.robots - 1}:")
    for key, rec in summary.recognition.items():
        rates = " ".join("  - " if r is None else f"{100 * r:4.1f}" for r in rec.rate)
        print(f"  {key:<14} {rates}")
    b = summary.bytes
    print(
        f"bytes between robots per round: {b.classifier_output_bytes_per_round:.0f} "
        f"({b.classifier_output_messages_per_round:.0f} ClassifierOutput messages)"
    )
    print(f"core check: largest posterior difference {checks.core_max_difference}")
    print(f"report: {args.out / 'report.md'}")
    return 0 if summary.complete else 1
