"""The Kubernetes deployment: the swarm's kustomize manifests (``k8s/``) in a namespace.

:class:`KubernetesDeployment` is the :class:`~swarmrec.deployments.base.Deployment`
of a swarm on a cluster. ``start(spec)``:

1. renders an overlay of this run into ``<out>/overlay/`` on top of a given one
   (``k8s/overlays/local`` by default): the namespace, each robot StatefulSet's
   ``replicas`` = the spec's robots, the ``swarm`` ConfigMap holding every setting
   the robots' services share (generated from the spec's components, as the compose
   file's environment is; :func:`cluster_spec`: index shards may have ids up to
   ``max_robots``, so ``kubectl scale statefulset/index-shard`` needs nothing else),
   the index shards' termination grace period from the spec's drain timeout
   (:func:`termination_grace_s`), and the detectors' dataset as a ConfigMap (a zip,
   at most 1 MiB) instead of the synthetic world the static overlays make in each pod;
2. applies the namespace and the Services first, and reads the router's and the
   gateway's ClusterIPs;
3. makes the swarm's PKI in ``<out>/pki`` (:func:`kubernetes_pki`: the router's
   certificate names ``router.<namespace>.svc`` and its ClusterIP, the gateway's
   likewise; certificates for ``max_robots`` robots, so the StatefulSets can scale
   up to it) and turns it into Secrets (:func:`secret_objects`; ``ca.key`` never
   leaves this machine);
4. applies everything (server-side apply), waits for every rollout.

The host reaches the swarm through the Services' ClusterIPs (kube-proxy programs
them on the node): :meth:`~KubernetesDeployment.client` connects to the router as the
operator (or a read-only client), :meth:`~KubernetesDeployment.gateway_client` to the
gRPC gateway, and :meth:`~KubernetesDeployment.metrics` reads the services' counters
from the swarm's Prometheus, less those at start. :meth:`~KubernetesDeployment.stop`
removes the namespace (and the node folders of the local overlay's volumes) unless
told to keep it; a kept swarm leaves ``<out>/swarm.json`` (:class:`KubernetesFile`),
so ``swarmrec run --attach <out>`` replays through it again.

Identities (docs/kubernetes.md, "Identities"): one Secret per robot service kind
holds every robot's pair of that kind; only a short init container of each pod
mounts it, and copies the pod's own pair into a memory volume, the only one the
service's container sees (:func:`swarmrec.security.install.install_identity`).
"""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import swarmrec
from swarmrec.client import GatewayClient, ZenohClient
from swarmrec.deployments.base import AttachFile, DeploymentError, SwarmSpec, numerics_env
from swarmrec.deployments.identities import client_tls, swarm_pki
from swarmrec.deployments.k8s_workloads import (
    detections_of,
    made_here,
    pod_inputs,
    robot_kinds_of,
    workload_objects,
)
from swarmrec.deployments.metrics import Scrape, scrape_prometheus
from swarmrec.deployments.pod_status import not_ready_containers, not_ready_report, selector_of
from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import to_env
from swarmrec.runtime.tls import ACL_FILE, tls_endpoint
from swarmrec.security.certs import load_certificate, sans_of
from swarmrec.security.identity import Identity
from swarmrec.services import registry
from swarmrec.services.settings import DetectorSettings, IndexSettings

__all__ = [
    "ACL_SECRET",
    "DEFAULT_OVERLAY",
    "K8S_DIR",
    "STOP_MARGIN_S",
    "Identities",
    "Kubectl",
    "KubernetesDeployment",
    "KubernetesError",
    "KubernetesFile",
    "KubernetesSettings",
    "cluster_spec",
    "install_identities",
    "kubernetes_pki",
    "make_secrets",
    "max_shards_of",
    "overlay_document",
    "read_kubernetes_file",
    "secret_name",
    "secret_names",
    "secret_objects",
    "service_names",
    "shared_env",
    "swarm_of",
    "termination_grace_s",
    "write_overlay",
]

Obj = dict[str, Any]

#: The repository's manifests (an installed package without its repository passes an overlay).
K8S_DIR = Path(__file__).resolve().parents[2] / "k8s"
DEFAULT_OVERLAY = K8S_DIR / "overlays" / "local"
ROUTER_PORT, GATEWAY_PORT, PROMETHEUS_PORT = 7447, 50051, 9090
#: The robot kinds the manifests run, one StatefulSet each.
ROBOT_KINDS: tuple[str, ...] = registry.WORKLOADS["places"]
#: Secrets: ``swarmrec-tls-<kind>`` (router, gateway, each robot kind) and the router's access control.
SECRET_PREFIX, ACL_SECRET = "swarmrec-tls-", "swarmrec-acl"
#: Where the detector's dataset ConfigMap is mounted (k8s/base/robots.yaml mounts its volume there).
DATASET_MOUNT = "/data"
DATASET_CONFIGMAP = "dataset"
#: What a ConfigMap holds at most (the apiserver refuses a larger one).
CONFIGMAP_LIMIT = 1 << 20
FIELD_MANAGER = "swarmrec"
#: What an index shard's stop may take besides its drain: the 15 s every robot service gets
#: to stop (k8s/base/robot-pod.yaml) and as much again for a loaded node (k8s/base/index-shard-stop.yaml).
STOP_MARGIN_S = 30
#: Settings that differ per pod or are the manifests' own (addresses, identity, storage, the
#: dataset's path in the pod): never in the shared ConfigMap.
PER_POD = frozenset(
    "SWARMREC_" + n.upper()
    for n in (
        "robot",
        "mode",
        "connect",
        "listen",
        "metrics_port",
        "metrics_host",
        "data_dir",
        "fsync",
        "security",
        "pki_dir",
        "identity",
        "insecure_reason",
        "dataset",
        "labels_file",
    )
)


class KubernetesError(DeploymentError):
    """kubectl failed, or the swarm did not come up on the cluster."""


def secret_name(who: str) -> str:
    """The Secret holding ``who``'s identities: a robot kind, ``router`` or ``gateway``."""
    return SECRET_PREFIX + who


def secret_names(kinds: Sequence[str] = ROBOT_KINDS) -> list[str]:
    """Every Secret :func:`make_secrets` makes for a swarm running ``kinds`` on its robots."""
    return [secret_name("router"), ACL_SECRET, secret_name("gateway"), *(secret_name(k) for k in kinds)]


def service_names(service: str, namespace: str) -> tuple[str, ...]:
    """The DNS names a Service is dialled at from inside the cluster (the pods use
    ``<service>.<namespace>.svc``; the last one assumes the default cluster domain)."""
    return (
        service,
        f"{service}.{namespace}",
        f"{service}.{namespace}.svc",
        f"{service}.{namespace}.svc.cluster.local",
    )


# --- kubectl ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Kubectl:
    """How this machine runs kubectl: the command (``kubectl``, or a wrapper such as
    ``deploy/k8s/kubectl.sh``) and, optionally, the kubeconfig."""

    command: tuple[str, ...] = ("kubectl",)
    kubeconfig: Path | None = None

    def argv(self, *args: str) -> list[str]:
        config = ["--kubeconfig", str(self.kubeconfig)] if self.kubeconfig is not None else []
        return [*self.command, *config, *args]

    def run(self, *args: str, stdin: str | None = None, timeout_s: float = 120.0, check: bool = True) -> str:
        cmd = self.argv(*args)
        try:
            done = subprocess.run(
                cmd, input=stdin, capture_output=True, text=True, timeout=timeout_s, check=False
            )
        except FileNotFoundError:
            raise KubernetesError(f"{cmd[0]}: not found (install kubectl, or pass --kubectl)") from None
        except subprocess.TimeoutExpired:
            raise KubernetesError(f"kubectl {' '.join(args[:4])} did not finish in {timeout_s:g} s") from None
        if check and done.returncode != 0:
            raise KubernetesError(
                f"kubectl {' '.join(args[:6])} failed ({done.returncode}):\n{done.stderr[-3000:]}"
            )
        return done.stdout

    def json(self, *args: str, timeout_s: float = 120.0) -> Any:
        return json.loads(self.run(*args, "-o", "json", timeout_s=timeout_s))

    def objects(self, yaml_text: str) -> list[Obj]:
        """Kubernetes YAML as objects, converted by kubectl without a cluster (the project has
        no YAML library): ``patch --local`` with an empty patch prints them as JSON."""
        out = self.run(
            "patch", "--local", "-f", "-", "-p", "{}", "--type", "merge", "-o", "json", stdin=yaml_text
        )
        decoder, i = json.JSONDecoder(), 0
        objects: list[Obj] = []
        while True:
            while i < len(out) and out[i].isspace():
                i += 1
            if i == len(out):
                return objects
            obj, i = decoder.raw_decode(out, i)
            objects.extend(obj["items"] if obj.get("kind") == "List" else [obj])

    def render(self, folder: Path) -> list[Obj]:
        """``kubectl kustomize folder``, as objects."""
        return self.objects(self.run("kustomize", str(folder)))

    def apply(self, objects: Sequence[Obj], timeout_s: float = 300.0) -> None:
        """Server-side apply (no last-applied annotation: a Secret's data is not copied into
        one, and a dataset ConfigMap may be larger than annotations allow)."""
        doc = json.dumps({"apiVersion": "v1", "kind": "List", "items": list(objects)})
        self.run(
            "apply", "--server-side", "--force-conflicts", f"--field-manager={FIELD_MANAGER}", "-f", "-",
            stdin=doc, timeout_s=timeout_s,
        )  # fmt: skip


# --- identities ---------------------------------------------------------------------------


def kubernetes_pki(
    folder: Path,
    swarm: str,
    robots: int,
    namespace: str,
    *,
    router_names: Sequence[str] = (),
    gateway_names: Sequence[str] = (),
) -> Path:
    """The swarm's PKI in ``folder`` for a swarm in ``namespace``: certificates for ``robots``
    robots, the router's and the gateway's naming their Services' DNS names (and
    ``router_names``/``gateway_names``: ClusterIPs, external names). A router or gateway
    certificate that lacks a wanted name (a Service recreated with another ClusterIP) is
    reissued; every other file is kept as :func:`~swarmrec.security.pki.init_pki` keeps it."""
    routers = (*service_names("router", namespace), *router_names)
    gateways = (*service_names("gateway", namespace), *gateway_names)
    for ident, names in ((Identity.router(swarm), routers), (Identity.client(swarm, "gateway"), gateways)):
        cert, key = folder / f"{ident.common_name}.pem", folder / f"{ident.common_name}.key"
        if cert.is_file() and not {n.lower() for n in names} <= sans_of(load_certificate(cert)):
            cert.unlink()
            key.unlink(missing_ok=True)
    return swarm_pki(folder, swarm, robots, router_names=routers, gateway_names=gateways)


def _secret(name: str, namespace: str, swarm: str, files: dict[str, bytes]) -> Obj:
    return {
        "apiVersion": "v1",
        "kind": "Secret",
        "type": "Opaque",
        "metadata": {
            "name": name,
            "namespace": namespace,
            "labels": {"app.kubernetes.io/part-of": "swarmrec", "swarmrec.io/swarm": swarm},
        },
        "data": {k: base64.b64encode(v).decode() for k, v in files.items()},
    }


def secret_objects(
    pki: Path, swarm: str, robots: int, namespace: str, kinds: Sequence[str] = ROBOT_KINDS
) -> list[Obj]:
    """The swarm's Secrets from its PKI folder: the router's pair, its access control, the
    gateway's pair, and per robot kind every robot's pair (each with ``ca.pem``; never
    ``ca.key``)."""

    def pairs(*cns: str) -> dict[str, bytes]:
        out = {"ca.pem": (pki / "ca.pem").read_bytes()}
        for cn in cns:
            out[f"{cn}.pem"] = (pki / f"{cn}.pem").read_bytes()
            out[f"{cn}.key"] = (pki / f"{cn}.key").read_bytes()
        return out

    spec = registry.spec
    objs = [
        _secret(secret_name("router"), namespace, swarm, pairs(spec("router").common_name(swarm, 0))),
        _secret(ACL_SECRET, namespace, swarm, {ACL_FILE: (pki / ACL_FILE).read_bytes()}),
        _secret(secret_name("gateway"), namespace, swarm, pairs(spec("gateway").common_name(swarm, 0))),
    ]
    for kind in kinds:
        cns = [spec(kind).common_name(swarm, r) for r in range(robots)]
        objs.append(_secret(secret_name(kind), namespace, swarm, pairs(*cns)))
    for obj in objs:
        size = sum(len(v) for v in obj["data"].values()) * 3 // 4
        if size > CONFIGMAP_LIMIT:
            raise ConfigError(
                f"Secret {obj['metadata']['name']} would hold {size} bytes, more than a Secret may "
                f"(1 MiB): {robots} robots are too many for one Secret per kind"
            )
    return objs


def make_secrets(
    kubectl: Kubectl,
    pki: Path,
    swarm: str,
    robots: int,
    namespace: str,
    kinds: Sequence[str] = ROBOT_KINDS,
) -> list[str]:
    """Create (or update) the Secrets of a swarm running ``kinds`` in ``namespace``; their names."""
    objs = secret_objects(pki, swarm, robots, namespace, kinds)
    kubectl.apply(objs)
    return [o["metadata"]["name"] for o in objs]


@dataclass(frozen=True)
class Identities:
    """What :func:`install_identities` made: a swarm's PKI on this machine and its Secrets."""

    namespace: str
    swarm: str
    #: Robots with certificates (and access-control rules): the most the StatefulSets may scale to.
    robots: int
    pki: Path
    #: ClusterIP of each Service of the namespace (the router's and gateway's are in their certificates).
    cluster_ips: dict[str, str]
    secrets: list[str]


def swarm_of(objects: Sequence[Obj]) -> tuple[str, str, int]:
    """The namespace, swarm name and robot count of a rendered overlay (its ``swarm`` ConfigMap)."""
    namespaces = {o["metadata"]["namespace"] for o in objects if o["metadata"].get("namespace")}
    maps = [
        o
        for o in objects
        if o["kind"] == "ConfigMap"
        and "SWARMREC_SWARM" in o.get("data", {})
        and "SWARMREC_N_ROBOTS" in o["data"]
    ]
    if len(namespaces) != 1 or len(maps) != 1:
        raise ConfigError(
            "not a swarm overlay: expected one namespace and one ConfigMap with SWARMREC_SWARM and "
            f"SWARMREC_N_ROBOTS, found namespaces {sorted(namespaces)} and {len(maps)} such ConfigMaps"
        )
    data = maps[0]["data"]
    return namespaces.pop(), data["SWARMREC_SWARM"], int(data["SWARMREC_N_ROBOTS"])


def max_shards_of(objects: Sequence[Obj]) -> int:
    """The most index shards a rendered overlay's swarm may scale to: its ``SWARMREC_MAX_SHARDS``
    (the shards accept ids up to it, :class:`~swarmrec.services.settings.IndexSettings`), at
    least its robots."""
    _, _, robots = swarm_of(objects)
    (data,) = [
        o["data"] for o in objects if o["kind"] == "ConfigMap" and "SWARMREC_N_ROBOTS" in o.get("data", {})
    ]
    return max(robots, int(data.get("SWARMREC_MAX_SHARDS", "0") or "0"))


def install_identities(
    kubectl: Kubectl,
    objects: Sequence[Obj],
    pki: Path,
    *,
    max_robots: int = 0,
    router_names: Sequence[str] = (),
    gateway_names: Sequence[str] = (),
) -> Identities:
    """The identities of the swarm a rendered overlay describes: its Namespace and Services
    are applied first (their ClusterIPs go into the router's and gateway's certificates, so
    this machine can reach both by address), then the PKI is made or completed in ``pki`` for
    ``max_robots`` robots (at least the overlay's robots and its ``SWARMREC_MAX_SHARDS``, so
    every shard the StatefulSet may be scaled to has its identity), and the Secrets applied.
    The pods of the overlay, applied after, find them (a Secret for each of its robot kinds)."""
    namespace, swarm, _ = swarm_of(objects)
    robots = max(max_shards_of(objects), max_robots)
    kubectl.apply([o for o in objects if o["kind"] in ("Namespace", "Service")])
    ips = {
        svc["metadata"]["name"]: svc["spec"].get("clusterIP", "")
        for svc in kubectl.json("-n", namespace, "get", "services")["items"]
    }
    for needed in ("router", "gateway"):
        if not ips.get(needed) or ips[needed] == "None":
            raise KubernetesError(f"the overlay has no {needed} Service with a ClusterIP")
    folder = kubernetes_pki(
        pki,
        swarm,
        robots,
        namespace,
        router_names=(ips["router"], *router_names),
        gateway_names=(ips["gateway"], *gateway_names),
    )
    names = make_secrets(kubectl, folder, swarm, robots, namespace, robot_kinds_of(objects) or ROBOT_KINDS)
    return Identities(namespace, swarm, robots, folder, ips, names)


# --- the overlay of one run ---------------------------------------------------------------


def cluster_spec(spec: SwarmSpec, max_robots: int) -> SwarmSpec:
    """``spec`` as it runs on a cluster whose certificates cover ``max_robots`` robots: its
    index shards accept ids up to ``max_robots - 1`` (``IndexSettings.max_shards``), so
    ``kubectl scale statefulset/index-shard --replicas=N`` up to it needs nothing else (the
    elastic index places label groups on whichever shards are alive). ``max_robots`` 0 (a
    swarm file written before this was recorded): ``spec`` as it is."""
    index = spec.component(IndexSettings)
    index = index if isinstance(index, IndexSettings) else IndexSettings()
    if max_robots <= 0 or index.max_shards == max_robots:
        return spec
    others = tuple(c for c in spec.components if not isinstance(c, IndexSettings))
    return replace(spec, components=(*others, index.with_(max_shards=max_robots)))


def termination_grace_s(spec: SwarmSpec) -> int:
    """The index shards' ``terminationGracePeriodSeconds``. A shard told to stop (scaled down,
    its pod deleted or evicted) first drains: it hands its label groups to the shards that stay
    while it still answers, for up to ``drain_timeout_s``; then it stops as every service does.
    The kubelet kills what still runs when the grace ends, and a shard killed mid-drain leaves
    its groups a replica short (possibly none, when both owners go) until it comes back. So the
    drain, and :data:`STOP_MARGIN_S` for the rest of the stop."""
    index = spec.component(IndexSettings)
    drain = index.drain_timeout_s if isinstance(index, IndexSettings) else IndexSettings().drain_timeout_s
    return math.ceil(drain) + STOP_MARGIN_S


def shared_env(spec: SwarmSpec) -> dict[str, str]:
    """Every setting the spec's robot services read, as ``SWARMREC_*`` variables, less what the
    manifests set per pod: the ``swarm`` ConfigMap of a run (all settings, defaults too, so a
    value of the overlay below never outlives the spec)."""
    out: dict[str, str] = {}
    for kind in spec.kinds:
        for part in spec.config_for(kind, 0).parts:
            out.update(to_env(part))
    return {k: v for k, v in sorted(out.items()) if k not in PER_POD}


def dataset_files(spec: SwarmSpec, folder: Path) -> dict[str, str]:
    """The detectors' dataset (and label list) written into ``folder`` for a ConfigMap:
    ``{file name: the path the detectors read it at}``. A dataset folder is zipped; a zip is
    zipped again at the highest compression (the TUM constellations' 1.06 MB zip becomes
    0.94 MB), since a ConfigMap holds at most 1 MiB."""
    detector = spec.component(DetectorSettings)
    if not isinstance(detector, DetectorSettings) or not detector.dataset:
        raise ConfigError("a Kubernetes swarm replays a dataset: the spec names none")
    if detector.detector_mode != "replay":
        raise ConfigError(
            f"a Kubernetes swarm's detectors replay constellations; {detector.detector_mode} mode "
            "runs on a local deployment"
        )
    source, target = Path(detector.dataset), folder / "dataset.zip"
    with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as out:
        if source.is_dir():
            # The frames only, as the detector reads a folder (a synthetic world's other .txt
            # files, groundtruth.txt and world.txt, are not frames; in a zip they would be read).
            frames = source / "constellations" if (source / "constellations").is_dir() else source
            for path in sorted(frames.glob("*.txt")):
                out.write(path, f"constellations/{path.name}")
        else:
            with zipfile.ZipFile(source) as given:
                for info in given.infolist():
                    if not info.is_dir():
                        out.writestr(info.filename, given.read(info))
    files = {"dataset.zip": f"{DATASET_MOUNT}/dataset.zip"}
    if detector.labels_file is not None:
        shutil.copy2(detector.labels_file, folder / "labels.txt")
        files["labels.txt"] = f"{DATASET_MOUNT}/labels.txt"
    size = sum((folder / f).stat().st_size for f in files)
    if size > CONFIGMAP_LIMIT - 4096:
        raise ConfigError(
            f"the dataset takes {size / 1e6:.2f} MB compressed; a ConfigMap holds 1 MiB: replay fewer "
            "frames (--frames) or mount the dataset into the detectors yourself"
        )
    return files


def detector_patch(files: dict[str, str]) -> Obj:
    """The detector StatefulSet replays the run's dataset ConfigMap instead of the synthetic
    world its init container would make."""
    env = [{"name": "SWARMREC_DATASET", "value": files["dataset.zip"]}]
    if "labels.txt" in files:
        env.append({"name": "SWARMREC_LABELS_FILE", "value": files["labels.txt"]})
    return {
        "apiVersion": "apps/v1",
        "kind": "StatefulSet",
        "metadata": {"name": "detector"},
        "spec": {
            "template": {
                "spec": {
                    "initContainers": [{"name": "synthetic-world", "$patch": "delete"}],
                    "containers": [{"name": "service", "env": env}],
                    "volumes": [
                        {"name": "dataset", "emptyDir": None, "configMap": {"name": DATASET_CONFIGMAP}}
                    ],
                }
            }
        },
    }


def index_shard_patch(spec: SwarmSpec) -> Obj:
    """The index shards' grace period for this run's drain timeout (:func:`termination_grace_s`)."""
    return {
        "apiVersion": "apps/v1",
        "kind": "StatefulSet",
        "metadata": {"name": "index-shard"},
        "spec": {"template": {"spec": {"terminationGracePeriodSeconds": termination_grace_s(spec)}}},
    }


def overlay_document(spec: SwarmSpec, namespace: str, base: str, files: dict[str, str]) -> Obj:
    """The kustomization of one run on top of the overlay at the relative path ``base``
    (``files``: the replaying detectors' dataset; none for a spec whose robot StatefulSets
    are made after rendering, :mod:`swarmrec.deployments.k8s_workloads`)."""
    literals = {**shared_env(spec), **numerics_env()}
    generators: list[Obj] = [
        {"name": "swarm", "behavior": "merge", "literals": [f"{k}={v}" for k, v in literals.items()]}
    ]
    patches = [{"path": "index-shard.json", "target": {"kind": "StatefulSet", "name": "index-shard"}}]
    if files:
        generators.append({"name": DATASET_CONFIGMAP, "files": sorted(files)})
        patches.insert(0, {"path": "detector.json", "target": {"kind": "StatefulSet", "name": "detector"}})
    return {
        "apiVersion": "kustomize.config.k8s.io/v1beta1",
        "kind": "Kustomization",
        "namespace": namespace,
        "resources": [base],
        # The kinds the manifests have; the others' StatefulSets are made with the spec's robots.
        "replicas": [{"name": kind, "count": spec.robots} for kind in spec.kinds if kind in ROBOT_KINDS],
        "configMapGenerator": generators,
        "patches": patches,
    }


def write_overlay(spec: SwarmSpec, namespace: str, overlay: Path, folder: Path) -> Path:
    """The overlay of one run in ``folder`` (emptied first): its kustomization on top of
    ``overlay``, the detector's patch and the dataset's files; returns ``folder``."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    files: dict[str, str] = {}
    if not made_here(spec):
        files = dataset_files(spec, folder)
        (folder / "detector.json").write_text(json.dumps(detector_patch(files), indent=1) + "\n")
    (folder / "index-shard.json").write_text(json.dumps(index_shard_patch(spec), indent=1) + "\n")
    # The settings as the pods read them: host paths become the pods' (k8s_workloads.pod_inputs).
    pods = pod_inputs(spec).spec
    doc = overlay_document(pods, namespace, os.path.relpath(overlay.resolve(), folder.resolve()), files)
    # JSON is YAML: kustomize reads it, and nothing needs a YAML library.
    (folder / "kustomization.yaml").write_text(
        f"# Generated by swarmrec {swarmrec.__version__} (swarmrec/deployments/kubernetes.py): "
        f"{spec.robots} robots, swarm {spec.swarm!r}.\n" + json.dumps(doc, indent=1) + "\n"
    )
    return folder


def _hostpath_roots(objects: Sequence[Obj]) -> set[Path]:
    """The node folders of volumes kept per namespace and pod (the local overlay's
    ``<root>/$(POD_NAMESPACE)/$(POD_NAME)``)."""
    roots = set()
    for obj in objects:
        if obj["kind"] != "StatefulSet":
            continue
        pod = obj["spec"]["template"]["spec"]
        volumes = {v["name"]: v for v in pod.get("volumes", [])}
        for c in pod.get("containers", []):
            for m in c.get("volumeMounts", []):
                host = volumes.get(m["name"], {}).get("hostPath")
                if host and m.get("subPathExpr", "").startswith("$(POD_NAMESPACE)/"):
                    roots.add(Path(host["path"]))
    return roots


# --- the deployment -----------------------------------------------------------------------


@dataclass(frozen=True)
class KubernetesSettings:
    """Where and how a spec becomes a namespace of a cluster; validated on construction."""

    namespace: str = "swarmrec-run"
    #: This run's overlay, PKI and swarm.json.
    out: Path = Path("runs/k8s")
    #: The overlay the run's own goes on top of.
    overlay: Path = DEFAULT_OVERLAY
    kubectl: Kubectl = field(default_factory=Kubectl)
    #: Certificates (and access-control rules) for this many robots, so the robot StatefulSets
    #: can be scaled up to it; 0: the spec's robots.
    max_robots: int = 0
    #: Seconds to wait for every rollout.
    wait_s: float = 600.0
    #: Leave the swarm running when the run stops (``swarmrec k8s down`` removes it).
    keep: bool = False

    def with_(self, **changes: Any) -> KubernetesSettings:
        return replace(self, **changes)

    def __post_init__(self) -> None:
        ns = self.namespace
        if not (0 < len(ns) <= 63 and ns[0].isalnum() and ns[-1].isalnum()) or not all(
            c.islower() or c.isdigit() or c == "-" for c in ns
        ):
            raise ConfigError(f"namespace must be 1-63 of a-z 0-9 - (a DNS label), got {ns!r}")
        if self.max_robots < 0:
            raise ConfigError(f"max_robots must be >= 0, got {self.max_robots}")
        if not (self.overlay / "kustomization.yaml").is_file():
            raise ConfigError(f"{self.overlay}: no kustomization.yaml (pass the overlay to build on)")


@dataclass(frozen=True, kw_only=True)
class KubernetesFile(AttachFile):
    """``swarm.json`` of a swarm on Kubernetes: the attach file, and where it runs."""

    deployment: str = "kubernetes"
    namespace: str
    #: The overlay it was built on, and how this machine runs kubectl.
    overlay: str
    kubectl: list[str]
    kubeconfig: str = ""
    #: Node folders of its volumes (removed with it).
    node_volumes: list[str] = field(default_factory=list)
    #: Robots with certificates, the most index shards it scales to (0: written before it was kept).
    max_robots: int = 0


def read_kubernetes_file(folder: Path) -> KubernetesFile:
    """The ``swarm.json`` a :class:`KubernetesDeployment` kept in ``folder``."""
    path = folder / "swarm.json"
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict) or data.get("deployment") != "kubernetes":
            raise ConfigError(f"{path} does not describe a swarm on Kubernetes")
        return KubernetesFile(**data)
    except FileNotFoundError:
        raise ConfigError(
            f"{path} not found: start the swarm first with `swarmrec k8s up --out {folder}`"
        ) from None
    except (json.JSONDecodeError, TypeError) as e:
        raise ConfigError(f"{path} is not a swarm file written by this version of swarmrec: {e}") from None


def _wait_tcp(host: str, port: int, timeout_s: float) -> None:
    """Until a TCP connection to a Service opens (kube-proxy programs it a moment after the
    pods are ready)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=2.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise KubernetesError(
                    f"{host}:{port} does not accept connections after {timeout_s:g} s"
                ) from None
            time.sleep(0.2)


class KubernetesDeployment:
    """A swarm in a Kubernetes namespace (see the module docstring)."""

    #: An operator may scale the robots' StatefulSets while a run replays.
    fixed_size = False
    emulated_links = None
    mesh = None

    def __init__(self, settings: KubernetesSettings, *, info: KubernetesFile | None = None) -> None:
        self.settings = settings
        self.kubectl = settings.kubectl
        self.namespace = settings.namespace
        self.description = f"kubernetes namespace {self.namespace}"
        #: Set once the swarm runs (read back from swarm.json when attached).
        self.info: KubernetesFile | None = info
        self.created = False
        self.spec: SwarmSpec | None = None
        self.timings: dict[str, float] = {}
        self._baseline: Scrape | None = None
        self._progress = False
        #: Node folders of the namespace's volumes, removed with it.
        self._volumes: list[str] = list(info.node_volumes) if info is not None else []
        #: The rgbd detectors' node folders by robot (copied back at stop).
        self._detections: dict[int, Path] = {}
        self._node_roots: list[Path] | None = None
        self._attached = info is not None

    @classmethod
    def attached(cls, folder: Path) -> KubernetesDeployment:
        """The swarm a kept deployment (``swarmrec k8s up --out folder``) left running."""
        info = read_kubernetes_file(folder)
        kubectl = Kubectl(tuple(info.kubectl), Path(info.kubeconfig) if info.kubeconfig else None)
        settings = KubernetesSettings(
            namespace=info.namespace, out=folder, overlay=Path(info.overlay), kubectl=kubectl, keep=True
        )
        return cls(settings, info=info)

    # --- where the swarm is ---------------------------------------------------------------

    def _info(self) -> KubernetesFile:
        if self.info is None:
            raise ConfigError("the swarm has not been started")
        return self.info

    @property
    def endpoint(self) -> str:
        return self._info().router_endpoint

    @property
    def gateway_address(self) -> str:
        return self._info().gateway_address

    @property
    def pki_dir(self) -> Path:
        return Path(self._info().pki_dir)

    def client(self, timeout_s: float = 5.0, *, role: str = "operator") -> ZenohClient:
        info = self._info()
        tls = client_tls(self.pki_dir, info.swarm, "client" if role == "client" else "operator")
        return ZenohClient([info.router_endpoint], info.swarm, timeout_s=timeout_s, tls=tls)

    def gateway_client(self, timeout_s: float = 5.0) -> GatewayClient:
        info = self._info()
        tls = client_tls(self.pki_dir, info.swarm, "client")
        return GatewayClient(info.gateway_address, info.swarm, timeout_s=timeout_s, tls=tls)

    def k(self, *args: str, timeout_s: float = 120.0) -> str:
        """kubectl in the swarm's namespace."""
        return self.kubectl.run("-n", self.namespace, *args, timeout_s=timeout_s)

    def _why_not_ready(self, workload: Obj) -> str:
        """What holds ``workload``'s pods (best effort: the cluster may be the problem)."""
        try:
            pods = self.kubectl.json("-n", self.namespace, "get", "pods", "-l", selector_of(workload))
            events = self.kubectl.json("-n", self.namespace, "get", "events")
        except (KubernetesError, ValueError) as e:
            return f"(could not read its pods: {e})"
        report = [not_ready_report(pods, events)]
        for pod, container, restarted in not_ready_containers(pods):
            args = ["logs", pod, "-c", container, "--tail", "8", *(["--previous"] if restarted else [])]
            try:
                tail = self.kubectl.run("-n", self.namespace, *args, timeout_s=30).rstrip()
            except KubernetesError as e:
                tail = f"(no log: {e})"
            report.append(f"log of {pod}/{container}{' (before its restart)' if restarted else ''}:\n{tail}")
        return "\n".join(report)

    # --- the Deployment interface ---------------------------------------------------------

    def start(self, spec: SwarmSpec, *, progress: bool = False) -> None:
        """Deploy ``spec`` into a new namespace (or, attached, check the running swarm is it)."""
        self._progress = progress
        self.spec = self._check(spec) if self.info is not None else self._deploy(spec)
        self._baseline = scrape_prometheus(self._info().prometheus_url, fresh_after=time.time())

    def wait_ready(self, timeout_s: float = 120.0) -> None:
        """The router's Service accepts connections and every service of the spec is alive."""
        spec = self.spec
        if spec is None:
            raise ConfigError("start the swarm first")
        host, _, port = self.endpoint.removeprefix("tls/").rpartition(":")
        _wait_tcp(host, int(port), timeout_s)
        with self.client(5.0) as client:
            client.wait_for(spec.expected(), timeout_s)

    def metrics(self) -> Scrape:
        """The counters the swarm's Prometheus holds now, less those at :meth:`start`."""
        after = scrape_prometheus(self._info().prometheus_url, fresh_after=time.time())
        return after if self._baseline is None else after.minus(self._baseline)

    def stop(self) -> dict[str, int]:
        """Copy what the rgbd detectors wrote to :attr:`local_data_dir`, then remove the namespace
        this deployment created (unless ``keep``); no exit codes (the pods are the cluster's)."""
        if self.created:
            self._copy_detections()
        if self.created and not self.settings.keep:
            self.remove()
        return {}

    @property
    def local_data_dir(self) -> Path | None:
        """Where the run reads what the detectors wrote (``robot<r>/detector``, as a local run lays
        it out), copied there from their node folders when the swarm stops: ``<out>/data`` when
        this deployment starts the swarm on an overlay that keeps volumes on this node; None for
        a swarm attached to, or one whose volumes are claims elsewhere."""
        if self._attached:
            return None
        if self._node_roots is None:
            self._node_roots = sorted(_hostpath_roots(self.kubectl.render(self.settings.overlay)))
        return self.settings.out.resolve() / "data" if self._node_roots else None

    def _frames_folder(self, objects: Sequence[Obj], needed: bool) -> Path | None:
        """The node folder the detectors' RGB-D frames go in, when the spec has some; ConfigError
        when the overlay keeps nothing on the node."""
        if not needed:
            return None
        roots = sorted(_hostpath_roots(objects))
        if not roots:
            raise ConfigError(
                "detectors that read RGB-D frames get them from a node folder, and this overlay keeps no "
                f"volume on the node ({self.settings.overlay}): use k8s/overlays/local, or run from pixels "
                "on local processes"
            )
        return roots[0] / self.namespace / "frames"

    def _copy_detections(self) -> None:
        """The rgbd detectors' data folders, from the node into ``<out>/data/robot<r>/detector``."""
        if not self._detections:
            return
        target = self.settings.out.resolve() / "data"
        shutil.rmtree(target, ignore_errors=True)
        for robot, folder in self._detections.items():
            if folder.is_dir():
                shutil.copytree(folder, target / f"robot{robot}" / "detector")

    # --- deploying ------------------------------------------------------------------------

    def _say(self, what: str) -> None:
        if self._progress:
            print(f"k8s: {what}", file=sys.stderr, flush=True)

    def _check(self, spec: SwarmSpec) -> SwarmSpec:
        """The running swarm is ``spec`` (as deployed: :func:`cluster_spec`), or ConfigError."""
        info, problems = self._info(), []
        spec = cluster_spec(spec, info.max_robots)
        if spec.workload and spec.workload != info.workload:
            problems.append(f"it runs the {info.workload} workload, not {spec.workload}")
        if tuple(info.kinds) != spec.kinds or info.robots != spec.robots or info.swarm != spec.swarm:
            problems.append(
                f"it is swarm {info.swarm!r} of {info.robots} robots running {info.kinds}, "
                f"not {spec.swarm!r} of {spec.robots} running {list(spec.kinds)}"
            )
        wanted = shared_env(spec)
        differ = sorted(
            k for k in wanted.keys() | info.shared_env.keys() if wanted.get(k) != info.shared_env.get(k)
        )
        if differ and not problems:
            shown = ", ".join(
                f"{k}={info.shared_env.get(k)!r} (wanted {wanted.get(k)!r})" for k in differ[:5]
            )
            problems.append(f"its settings differ: {shown}")
        if problems:
            raise ConfigError(
                f"the swarm in namespace {info.namespace} is not this run's: " + "; ".join(problems)
            )
        return spec

    def _deploy(self, spec: SwarmSpec) -> SwarmSpec:
        """Deploy ``spec`` (as :func:`cluster_spec` makes it for the certificates' robots)."""
        s, t0 = self.settings, time.monotonic()
        if spec.swarm_kinds != ("gateway",):
            raise ConfigError(
                f"the Kubernetes manifests run a router and a gateway for the swarm, not {spec.swarm_kinds}"
            )
        if 0 < s.max_robots < spec.robots:
            raise ConfigError(f"max_robots ({s.max_robots}) is smaller than the swarm ({spec.robots} robots)")
        # Certificates for every shard the StatefulSet may be scaled to (a spec's own max_shards too).
        index = spec.component(IndexSettings)
        max_robots = max(
            s.max_robots, spec.robots, index.max_shards if isinstance(index, IndexSettings) else 0
        )
        spec = cluster_spec(spec, max_robots)
        out = s.out.resolve()
        objects = self.kubectl.render(write_overlay(spec, self.namespace, s.overlay, out / "overlay"))
        inputs = pod_inputs(spec)
        frames_on_node = self._frames_folder(objects, inputs.frames is not None)
        objects = workload_objects(objects, inputs, self.namespace, frames_on_node)
        self.timings["render_s"] = time.monotonic() - t0

        if self.kubectl.run("get", "namespace", self.namespace, "--ignore-not-found", "-o", "name").strip():
            raise ConfigError(
                f"namespace {self.namespace} exists: remove it (swarmrec k8s down) or choose another"
            )
        roots = _hostpath_roots(objects)
        for root in roots:
            if (root / self.namespace).exists():
                raise ConfigError(
                    f"{root / self.namespace} holds the data of an earlier swarm in namespace "
                    f"{self.namespace}: remove it, or choose another namespace"
                )
        self._say(f"namespace {self.namespace}: {len(objects)} objects; Services, PKI, Secrets first")
        t1 = time.monotonic()
        self._volumes = sorted(str(r / self.namespace) for r in roots)
        self.created = True  # from here on, stop() removes what was made
        if inputs.frames is not None and frames_on_node is not None:
            # The detectors' RGB-D frames, on the node (read-only in their pods).
            shutil.copytree(inputs.frames, frames_on_node)
        if inputs.frames is not None:
            self._detections = detections_of(objects, self.namespace, sorted(roots), spec.robots)
        ids = install_identities(self.kubectl, objects, out / "pki", max_robots=max_robots)
        ips, pki = ids.cluster_ips, ids.pki
        if not ips.get("prometheus") or ips["prometheus"] == "None":
            raise KubernetesError("the overlay has no prometheus Service with a ClusterIP")
        self.timings["pki_and_secrets_s"] = time.monotonic() - t1
        self._say(f"PKI in {pki} ({ids.robots} robots), Secrets {', '.join(ids.secrets)}; applying the swarm")

        t1 = time.monotonic()
        self.kubectl.apply(objects)
        deadline = time.monotonic() + s.wait_s
        for workload in (o for o in objects if o["kind"] in ("Deployment", "StatefulSet")):
            ref = f"{workload['kind'].lower()}/{workload['metadata']['name']}"
            left = max(deadline - time.monotonic(), 1.0)
            try:
                self.k("rollout", "status", ref, f"--timeout={left:.0f}s", timeout_s=left + 30)
            except KubernetesError as e:
                raise KubernetesError(f"{e}\n{self._why_not_ready(workload)}") from None
        # kube-proxy programs a Service a moment after its pods are ready.
        for name, port in (
            ("router", ROUTER_PORT),
            ("gateway", GATEWAY_PORT),
            ("prometheus", PROMETHEUS_PORT),
        ):
            _wait_tcp(ips[name], port, max(deadline - time.monotonic(), 30.0))
        self.timings["apply_to_ready_s"] = time.monotonic() - t1
        self._say(f"every rollout done and the Services answer in {time.monotonic() - t1:.1f} s")
        self.info = KubernetesFile(
            swarm=spec.swarm,
            robots=spec.robots,
            workload=spec.workload,
            kinds=list(spec.kinds),
            router_endpoint=tls_endpoint(ips["router"], ROUTER_PORT),
            prometheus_url=f"http://{ips['prometheus']}:{PROMETHEUS_PORT}",
            gateway_address=f"grpc://{ips['gateway']}:{GATEWAY_PORT}",
            pki_dir=str(pki),
            shared_env=shared_env(spec),
            namespace=self.namespace,
            overlay=str(s.overlay.resolve()),
            kubectl=list(self.kubectl.command),
            kubeconfig=str(self.kubectl.kubeconfig or ""),
            node_volumes=self._volumes,
            max_robots=ids.robots,
        )
        return spec

    def write_attach_file(self, experiment: dict[str, Any]) -> Path:
        """Write ``<out>/swarm.json`` (with the experiment's record) for ``--attach``; its path."""
        info = self._info()
        info = KubernetesFile(**{**asdict(info), "experiment": dict(experiment)})
        self.info = info
        path = self.settings.out / "swarm.json"
        path.write_text(json.dumps(asdict(info), indent=2) + "\n")
        return path

    def remove(self, timeout_s: float = 240.0) -> None:
        """Delete the namespace (every object, Secrets included) and the node folders of its
        volumes; the PKI on this machine stays in ``<out>/pki``."""
        self.kubectl.run(
            "delete", "namespace", self.namespace, "--ignore-not-found", "--wait=true",
            f"--timeout={timeout_s:.0f}s", timeout_s=timeout_s + 30,
        )  # fmt: skip
        for folder in self._volumes:
            shutil.rmtree(folder, ignore_errors=True)
            if Path(folder).exists():
                print(
                    f"k8s: could not remove {folder} (its owner is the pods' user): remove it as root",
                    file=sys.stderr,
                )
        self.created = False
