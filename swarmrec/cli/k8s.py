"""``swarmrec k8s up|down|secrets|identity``: the swarm on Kubernetes (docs/kubernetes.md).

* ``up``: a places swarm in a namespace of its own (the ``k8s/`` manifests, Secrets for
  every identity), left running; ``swarmrec run --attach OUT`` replays through it;
* ``down``: removes what ``up`` made;
* ``secrets``: the identities of any overlay (``kubectl apply -k`` deploys it after);
* ``identity``: what each pod's init container runs: installs the pod's own identity.

``identity`` runs in every pod at start, so this module imports the deployments only
in the commands that need them.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from swarmrec.cli.common import Subparsers, add_dataset_flags, swarm_places_settings

if TYPE_CHECKING:
    from swarmrec.deployments.kubernetes import Kubectl

__all__ = ["add", "add_cluster_flags", "kubectl_of", "run"]

#: The repository's wrapper of the project's own cluster (deploy/k8s/kubectl.sh).
_REPO_KUBECTL = Path(__file__).resolve().parents[2] / "deploy" / "k8s" / "kubectl.sh"


def add_cluster_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """How this machine reaches the cluster: shared by ``k8s`` and ``run --deployment k8s``."""
    p.add_argument(
        "--kubectl",
        help="the kubectl command, e.g. 'kubectl --context lab' (default: $SWARMREC_KUBECTL, else kubectl "
        "on PATH, else this repository's deploy/k8s/kubectl.sh, the project's own cluster)",
    )
    p.add_argument("--kubeconfig", type=Path, help="kubeconfig file (default: kubectl's own)")
    p.add_argument(
        "--overlay",
        type=Path,
        help="the kustomize overlay to build on (default: this repository's k8s/overlays/local)",
    )
    p.add_argument(
        "--max-robots",
        type=int,
        default=0,
        help="issue certificates and access-control rules for this many robots, so the robot "
        "StatefulSets can be scaled up to it (default: the swarm's robots)",
    )


def kubectl_of(args: argparse.Namespace) -> Kubectl:
    """The kubectl the flags (or the environment) name."""
    from swarmrec.deployments.kubernetes import Kubectl

    text = args.kubectl or os.environ.get("SWARMREC_KUBECTL", "")
    if text:
        command = tuple(shlex.split(text))
    elif shutil.which("kubectl") is None and _REPO_KUBECTL.is_file():
        command = (str(_REPO_KUBECTL),)
    else:
        command = ("kubectl",)
    return Kubectl(command, args.kubeconfig)


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "k8s",
        help="the swarm on Kubernetes: up, down, its Secrets, a pod's identity",
        description=(
            "up: deploy a places swarm of N robots into a new namespace (the k8s/ manifests, a PKI made "
            "for it and turned into Secrets, mutual TLS on every link), wait until every pod is ready, "
            "write OUT/swarm.json; `swarmrec run --attach OUT` replays through it. down: delete the "
            "namespace (and the node folders of its volumes). secrets: make the PKI and Secrets of an "
            "overlay (its Namespace and Services are applied first, so their ClusterIPs go into the "
            "certificates); then `kubectl apply -k OVERLAY`. identity: run by each pod's init container."
        ),
    )
    p.add_argument("action", choices=("up", "down", "secrets", "identity"))
    add_dataset_flags(p)
    add_cluster_flags(p)
    p.add_argument("--robots", type=int, default=3, help="up: robots (default 3)")
    p.add_argument("--namespace", default="swarmrec-k8s", help="up: the namespace (default swarmrec-k8s)")
    p.add_argument("--swarm", default="k8s", help="up: swarm name (default k8s)")
    p.add_argument("--free", action="store_true", help="up: for free replay (--pace fast or a rate)")
    p.add_argument("--timeout", type=float, default=5.0, help="up: seconds a service waits for a peer")
    p.add_argument("--out", type=Path, default=Path("runs/k8s"), help="up, down: folder (default runs/k8s)")
    p.add_argument("--pki-dir", type=Path, help="secrets: the PKI folder (default runs/k8s/<namespace>/pki)")
    p.add_argument("--router-names", default="", help="secrets: more names the router is dialled at")
    p.add_argument("--gateway-names", default="", help="secrets: more names the gateway is dialled at")
    p.add_argument("--kind", help="identity: the pod's service kind")
    p.add_argument(
        "--from",
        dest="source",
        type=Path,
        default=Path("/run/swarmrec/secrets"),
        help="identity: the mounted Secret (default /run/swarmrec/secrets)",
    )
    p.add_argument(
        "--to",
        dest="target",
        type=Path,
        default=Path("/run/swarmrec/pki"),
        help="identity: the folder the service reads (default /run/swarmrec/pki)",
    )
    p.set_defaults(handler=run)


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip())


def identity(args: argparse.Namespace) -> int:
    """The pod's own pair out of its kind's Secret; robot and swarm from its SWARMREC_* variables."""
    from swarmrec.errors import ConfigError
    from swarmrec.runtime.settings import BusSettings, load_config
    from swarmrec.runtime.tls import ACL_FILE
    from swarmrec.security.install import install_identity
    from swarmrec.services import registry
    from swarmrec.services.settings import IndexSettings

    if not args.kind:
        raise ConfigError("identity needs --kind")
    # The robot ids the kind's service accepts: index shards' go past the robots (max_shards),
    # so a shard StatefulSet scaled beyond SWARMREC_N_ROBOTS gets its identities too.
    entry = registry.spec(args.kind)
    bound = [c for c in entry.all_components if c is IndexSettings]
    bus = load_config([BusSettings, *bound]).bus
    cn = entry.common_name(bus.swarm, bus.robot)
    extra = [ACL_FILE]
    if entry.peer_certificates:
        # The other robots' certificates of its kind (public; the Secret holds every robot's): a
        # relayed message's origin signature is checked against its origin's (docs/security.md).
        extra += [f"{entry.common_name(bus.swarm, r)}.pem" for r in range(bus.n_robots) if r != bus.robot]
    written = install_identity(args.source, args.target, cn, extra=extra)
    print(f"identity {cn}: {', '.join(p.name for p in written)} in {args.target}")
    return 0


def secrets(args: argparse.Namespace) -> int:
    from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, install_identities, swarm_of

    kubectl = kubectl_of(args)
    overlay = args.overlay or DEFAULT_OVERLAY
    objects = kubectl.render(overlay)
    namespace, _, _ = swarm_of(objects)
    pki = args.pki_dir or Path("runs/k8s") / namespace / "pki"
    ids = install_identities(
        kubectl,
        objects,
        pki,
        max_robots=args.max_robots,
        router_names=_names(args.router_names),
        gateway_names=_names(args.gateway_names),
    )
    print(
        f"swarm {ids.swarm} in namespace {ids.namespace}: PKI for {ids.robots} robots in {ids.pki} "
        f"(keep {ids.pki / 'ca.key'} off the cluster); Secrets {', '.join(ids.secrets)}"
    )
    print(
        f"router {ids.cluster_ips['router']}:7447, gateway grpc://{ids.cluster_ips['gateway']}:50051; "
        f"now: kubectl apply -k {overlay}"
    )
    return 0


def up(args: argparse.Namespace) -> int:
    from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, KubernetesSettings
    from swarmrec.experiments.places.keep import kubernetes_up

    run = swarm_places_settings(args, args.out)
    settings = KubernetesSettings(
        namespace=args.namespace,
        out=args.out,
        overlay=args.overlay or DEFAULT_OVERLAY,
        kubectl=kubectl_of(args),
        max_robots=args.max_robots,
        keep=True,
    )
    deployment = kubernetes_up(run, settings)
    info = deployment.info
    assert info is not None  # set by a successful start
    took = sum(deployment.timings.values())
    print(f"swarm {info.swarm} of {info.robots} robots up in namespace {info.namespace} in {took:.1f} s:")
    print(
        f"  router {info.router_endpoint}, gateway {info.gateway_address}, Prometheus {info.prometheus_url}"
    )
    print(f"  PKI in {info.pki_dir}; replay through it: swarmrec run --attach {args.out}")
    return 0


def down(args: argparse.Namespace) -> int:
    from swarmrec.deployments.kubernetes import KubernetesDeployment

    deployment = KubernetesDeployment.attached(args.out)
    deployment.remove()
    (args.out / "swarm.json").unlink(missing_ok=True)
    print(f"namespace {deployment.namespace} removed (the PKI stays in {deployment.pki_dir})")
    return 0


def run(args: argparse.Namespace) -> int:
    handlers = {"identity": identity, "secrets": secrets, "up": up, "down": down}
    return handlers[args.action](args)
