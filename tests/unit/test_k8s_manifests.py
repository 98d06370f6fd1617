"""The Kubernetes manifests (k8s/): every rendered object is valid against Kubernetes' own
OpenAPI schemas, and the swarm they describe is consistent with the services' settings.

How the schemas are had, offline: the OpenAPI v3 documents of the exact release the project's
cluster runs are part of the Go module ``k8s.io/kubernetes`` (``api/openapi-spec/v3/``), which
``deploy/k8s/build-binaries.sh`` fetches from the Go module proxy into the project's cache, once,
to build the cluster. Nothing is vendored, no schema registry is asked, and the documents are
the apiserver's own, so a field the cluster would reject fails here first. ``kubectl kustomize``
(the cluster's kubectl, from the same cache) renders the overlays, and ``kubectl patch --local``
turns the YAML into JSON without a server. When the cache lacks either, the fixture builds
kubectl alone (a few minutes, the first time only).

What the schemas cannot say is checked against the code: every SWARMREC_* variable is a setting
the services read, each robot's environment loads with the services' own settings loader, the
robot StatefulSets agree with SWARMREC_N_ROBOTS, the images are the package's version, and the
selectors, references and volumes fit together. Identities: every swarm pod presents its own
certificate, copied by its init container (the only one to mount a Secret, read-only) from the
Secrets ``swarmrec k8s secrets`` makes, none of which holds ``ca.key``; probes are ``httpGet`` on the
services' own pages. ``tests/e2e/test_k8s_cluster.py`` deploys the local overlay on a real cluster
(server-side dry run first, then for real).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import pytest

import swarmrec
from swarmrec.deployments.kubernetes import secret_name, secret_names
from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import ENV_PREFIX, BusSettings, Config, StorageSettings, describe, load_config
from swarmrec.services import registry
from swarmrec.services.settings import DetectorSettings, GatewaySettings, PlaceSettings
from tests.conftest import REPO

OVERLAYS = ("local", "production")
ROBOT_KINDS = ("index-shard", "verifier", "descriptor", "detector")
STATEFUL_KINDS = ("index-shard", "verifier", "descriptor")
SWARM_KINDS = ("router", "gateway")
PKI_DIR = "/run/swarmrec/pki"
EXAMPLES = sorted((REPO / "k8s" / "examples").glob("*.yaml"))

Obj = dict[str, Any]


# --- the cluster's paths and tools (deploy/k8s/env.sh is the one place they are written) ---------------


@cache
def cluster_env() -> dict[str, str]:
    """deploy/k8s/env.sh's variables, as bash evaluates them here."""
    names = [
        "K8S_VERSION",
        "K8S_BIN",
        "K8S_SRC",
        "K8S_STATE",
        "K8S_VOLUMES",
        "KUBECONFIG_ADMIN",
        "SERVICE_CIDR",
    ]
    script = f". {REPO / 'deploy/k8s/env.sh'}; " + "; ".join(f'echo "${n}"' for n in names)
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, check=True).stdout
    return dict(zip(names, out.splitlines(), strict=True))


def ensure_kubectl() -> Path:
    """The cluster's kubectl and the release's source (its OpenAPI documents), built when missing."""
    env = cluster_env()
    kubectl = Path(env["K8S_BIN"]) / "kubectl"
    if not kubectl.is_file() or not (Path(env["K8S_SRC"]) / "api" / "openapi-spec" / "v3").is_dir():
        done = subprocess.run(
            [str(REPO / "deploy/k8s/build-binaries.sh"), "kubectl"],
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode != 0:
            pytest.fail(f"deploy/k8s/build-binaries.sh kubectl failed:\n{done.stderr[-3000:]}")
    return kubectl


def kubectl_run(*args: str, stdin: str | None = None, timeout_s: float = 120.0) -> str:
    """kubectl with no cluster at all (a kubeconfig that does not exist): rendering and conversion only."""
    done = subprocess.run(
        [str(ensure_kubectl()), *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env={**os.environ, "KUBECONFIG": "/nonexistent"},
    )
    if done.returncode != 0:
        raise AssertionError(f"kubectl {' '.join(args)} failed:\n{done.stderr}")
    return done.stdout


def yaml_to_objects(text: str) -> list[Obj]:
    """Kubernetes YAML as JSON objects, converted by kubectl (the project has no YAML library)."""
    out = kubectl_run("patch", "--local", "-f", "-", "-p", "{}", "--type", "merge", "-o", "json", stdin=text)
    decoder, objects, i = json.JSONDecoder(), [], 0
    while True:
        while i < len(out) and out[i].isspace():
            i += 1
        if i == len(out):
            return objects
        obj, i = decoder.raw_decode(out, i)
        objects.extend(obj["items"] if obj.get("kind") == "List" else [obj])


@cache
def rendered(overlay: str) -> tuple[Obj, ...]:
    """``kubectl kustomize k8s/overlays/<overlay>``, as objects."""
    return tuple(yaml_to_objects(kubectl_run("kustomize", str(REPO / "k8s" / "overlays" / overlay))))


# --- Kubernetes' OpenAPI v3 schemas, and a validator of what the apiserver checks structurally ----------


@cache
def openapi() -> tuple[dict[str, Obj], dict[tuple[str, str, str], str]]:
    """Every component schema of the release's OpenAPI v3 documents, and the schema of each kind."""
    ensure_kubectl()
    schemas: dict[str, Obj] = {}
    for path in sorted((Path(cluster_env()["K8S_SRC"]) / "api" / "openapi-spec" / "v3").glob("*.json")):
        schemas.update(json.loads(path.read_text()).get("components", {}).get("schemas", {}))
    by_kind = {
        (gvk["group"], gvk["version"], gvk["kind"]): name
        for name, schema in schemas.items()
        for gvk in schema.get("x-kubernetes-group-version-kind", [])
    }
    return schemas, by_kind


def _resolve(schema: Obj, schemas: dict[str, Obj]) -> Obj:
    """A schema with its $ref (the documents wrap them in a one-item allOf) followed."""
    while True:
        if "$ref" in schema:
            schema = schemas[schema["$ref"].rsplit("/", 1)[1]]
        elif "allOf" in schema and len(schema["allOf"]) == 1 and not schema.get("properties"):
            schema = schema["allOf"][0]
        else:
            return schema


def schema_errors(value: Any, schema: Obj, where: str, schemas: dict[str, Obj]) -> Iterator[str]:
    """Where ``value`` breaks ``schema``: types, required and unknown fields (the apiserver's strict
    field validation, kubectl's default), enums, int-or-string, formats of the quantity kind."""
    schema = _resolve(schema, schemas)
    if schema.get("x-kubernetes-preserve-unknown-fields") or not schema:
        return
    if schema.get("x-kubernetes-int-or-string"):
        if not isinstance(value, int | str) or isinstance(value, bool):
            yield f"{where}: {value!r} is neither an integer nor a string"
        return
    for alternatives in ("oneOf", "anyOf"):
        if alternatives in schema:
            options = [list(schema_errors(value, s, where, schemas)) for s in schema[alternatives]]
            if all(options):
                yield f"{where}: {value!r} matches none of {alternatives}"
            return
    kind = schema.get("type")
    if kind == "object" or "properties" in schema:
        if not isinstance(value, dict):
            yield f"{where}: expected an object, got {value!r}"
            return
        for name in schema.get("required", []):
            if name not in value:
                yield f"{where}: missing required field {name!r}"
        properties, extra = schema.get("properties", {}), schema.get("additionalProperties")
        for name, item in value.items():
            if name in properties:
                yield from schema_errors(item, properties[name], f"{where}.{name}", schemas)
            elif isinstance(extra, dict):
                yield from schema_errors(item, extra, f"{where}.{name}", schemas)
            elif extra is not True:
                yield f"{where}: unknown field {name!r}"
    elif kind == "array":
        if not isinstance(value, list):
            yield f"{where}: expected a list, got {value!r}"
            return
        for i, item in enumerate(value):
            yield from schema_errors(item, schema.get("items", {}), f"{where}[{i}]", schemas)
    elif kind == "string":
        if not isinstance(value, str):
            yield f"{where}: expected a string, got {value!r}"
        elif "enum" in schema and value not in schema["enum"]:
            yield f"{where}: {value!r} is not one of {schema['enum']}"
    elif kind == "integer":
        if not isinstance(value, int) or isinstance(value, bool):
            yield f"{where}: expected an integer, got {value!r}"
    elif kind == "number":
        if not isinstance(value, int | float) or isinstance(value, bool):
            yield f"{where}: expected a number, got {value!r}"
    elif kind == "boolean" and not isinstance(value, bool):
        yield f"{where}: expected a boolean, got {value!r}"


def validate(obj: Obj) -> list[str]:
    schemas, by_kind = openapi()
    group, _, version = obj["apiVersion"].rpartition("/")
    name = by_kind.get((group, version, obj["kind"]))
    where = f"{obj['kind']}/{obj['metadata'].get('name')}"
    if name is None:
        release = cluster_env()["K8S_VERSION"]
        return [f"{where}: {obj['apiVersion']} {obj['kind']} is not a kind of Kubernetes {release}"]
    return list(schema_errors(obj, schemas[name], where, schemas))


# --- helpers on the rendered objects ----------------------------------------------------------------


def find(objs: tuple[Obj, ...], kind: str, name: str) -> Obj:
    (found,) = [o for o in objs if o["kind"] == kind and o["metadata"]["name"] == name]
    return found


def workloads(objs: tuple[Obj, ...]) -> list[Obj]:
    return [o for o in objs if o["kind"] in ("Deployment", "StatefulSet")]


def pod_containers(workload: Obj) -> list[Obj]:
    spec = workload["spec"]["template"]["spec"]
    return list(spec.get("initContainers", [])) + list(spec["containers"])


def service_container(workload: Obj) -> Obj:
    (container,) = [c for c in workload["spec"]["template"]["spec"]["containers"] if c["name"] == "service"]
    return container


def swarm_config(objs: tuple[Obj, ...]) -> dict[str, str]:
    """The generated ConfigMap every robot service takes its settings from."""
    (cm,) = [o for o in objs if o["kind"] == "ConfigMap" and o["metadata"]["name"].startswith("swarm-")]
    return dict(cm["data"])


def environment(objs: tuple[Obj, ...], workload: Obj, container: Obj, robot: int) -> dict[str, str]:
    """A container's environment as the kubelet would make it for pod ``robot`` of ``workload``:
    ConfigMaps, values, the downward API (ordinal label, namespace, name) and ``$(VAR)`` expansion."""
    env: dict[str, str] = {}
    for source in container.get("envFrom", []):
        env.update(find(objs, "ConfigMap", source["configMapRef"]["name"])["data"])
    labels = {
        **workload["spec"]["template"]["metadata"]["labels"],
        "apps.kubernetes.io/pod-index": str(robot),
    }
    fields_ = {
        "metadata.namespace": workload["metadata"]["namespace"],
        "metadata.name": f"{workload['metadata']['name']}-{robot}",
        **{f"metadata.labels['{k}']": v for k, v in labels.items()},
    }
    for var in container.get("env", []):
        if "value" in var:
            env[var["name"]] = re.sub(
                r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", lambda m: env[m.group(1)], var["value"]
            )
        elif "fieldRef" in var["valueFrom"]:
            env[var["name"]] = fields_[var["valueFrom"]["fieldRef"]["fieldPath"]]
        else:
            ref = var["valueFrom"]["configMapKeyRef"]
            env[var["name"]] = find(objs, "ConfigMap", ref["name"])["data"][ref["key"]]
    return env


def robot_environment(objs: tuple[Obj, ...], kind: str, robot: int) -> dict[str, str]:
    """The environment of robot ``robot``'s ``kind`` service container."""
    sts = find(objs, "StatefulSet", kind)
    return environment(objs, sts, service_container(sts), robot)


def service_config(kind: str, env: dict[str, str], **flags: Any) -> Config:
    """``kind``'s whole configuration from ``env`` (and ``flags``), by the services' own loader."""
    entry = registry.spec(kind)
    overrides = {"mode": entry.zenoh_mode} if entry.zenoh_mode else {}
    return load_config(entry.all_components, env=env, overrides={**overrides, **flags})


VERSIONED_IMAGES = {f"swarmrec:{swarmrec.__version__}", f"swarmrec-prometheus:{swarmrec.__version__}"}
SETTING_VARIABLES = {info.env for comp in registry.all_components() for info in describe(comp)}


# --- the tests -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_rendered_object_is_valid_against_the_kubernetes_openapi_schemas(overlay: str) -> None:
    objs = rendered(overlay)
    assert len(objs) >= 20
    errors = [e for o in objs for e in validate(o)]
    assert errors == []


@pytest.mark.parametrize("example", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_the_example_manifests_are_valid_against_the_kubernetes_openapi_schemas(example: Path) -> None:
    objs = yaml_to_objects(example.read_text())
    assert objs and [e for o in objs for e in validate(o)] == []


def test_the_validator_rejects_what_the_apiserver_rejects() -> None:
    # The schema check is only worth something if it fails: an unknown field, a wrong type, a
    # missing required field. (Enum values are not in the published schemas; the apiserver checks
    # them, and tests/e2e/test_k8s_cluster.py has it check this overlay with a server-side dry run.)
    good = find(rendered("local"), "Deployment", "router")
    bad = json.loads(json.dumps(good))
    bad["spec"]["replicas"] = "1"
    container = bad["spec"]["template"]["spec"]["containers"][0]
    container["ports"][0]["containerPort"] = "7447"
    container["livenessProbe"]["httpGet"]["pathh"] = "/healthz"
    del container["name"]
    errors = validate(bad)
    assert validate(good) == []
    assert sorted(errors) == sorted(
        [
            "Deployment/router.spec.replicas: expected an integer, got '1'",
            "Deployment/router.spec.template.spec.containers[0]: missing required field 'name'",
            "Deployment/router.spec.template.spec.containers[0].livenessProbe.httpGet: unknown field 'pathh'",
            "Deployment/router.spec.template.spec.containers[0].ports[0].containerPort: "
            "expected an integer, got '7447'",
        ]
    )


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_each_robot_statefulset_has_as_many_replicas_as_the_swarm_has_robots(overlay: str) -> None:
    objs = rendered(overlay)
    robots = int(swarm_config(objs)["SWARMREC_N_ROBOTS"])
    assert {k: find(objs, "StatefulSet", k)["spec"]["replicas"] for k in ROBOT_KINDS} == dict.fromkeys(
        ROBOT_KINDS, robots
    )
    # One object per service kind, never one per robot (the index will scale by replicas).
    assert sorted(o["metadata"]["name"] for o in objs if o["kind"] == "StatefulSet") == sorted(ROBOT_KINDS)
    assert sorted(o["metadata"]["name"] for o in objs if o["kind"] == "Deployment") == [
        "gateway",
        "prometheus",
        "router",
    ]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_swarmrec_variable_is_a_setting_the_services_read(overlay: str) -> None:
    objs = rendered(overlay)
    named = set(swarm_config(objs))
    for w in workloads(objs):
        for c in pod_containers(w):
            named |= {v["name"] for v in c.get("env", [])}
    assert {n for n in named if n.startswith(ENV_PREFIX)} - SETTING_VARIABLES == set()


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_each_robots_environment_loads_with_the_services_own_settings_loader(overlay: str) -> None:
    objs = rendered(overlay)
    robots = int(swarm_config(objs)["SWARMREC_N_ROBOTS"])
    namespace = find(objs, "Service", "router")["metadata"]["namespace"]
    for kind in ROBOT_KINDS:
        for robot in (0, robots - 1):
            config = service_config(kind, robot_environment(objs, kind, robot))
            bus = config.bus
            assert (bus.robot, bus.n_robots, bus.metrics_port, bus.metrics_host) == (
                robot,
                robots,
                9464,
                "0.0.0.0",
            )
            # Mutual TLS to the router's Service by the DNS name its certificate carries.
            assert bus.connect == (f"tls/router.{namespace}.svc:7447",)
            if kind in STATEFUL_KINDS:
                assert config.get(StorageSettings).data_dir == Path("/var/lib/swarmrec")
    detector = service_config("detector", robot_environment(objs, "detector", 0))
    assert detector.get(DetectorSettings).dataset == "/data/dataset"


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_router_and_the_gateway_load_their_settings_too(overlay: str) -> None:
    objs = rendered(overlay)
    namespace = find(objs, "Service", "router")["metadata"]["namespace"]
    router = find(objs, "Deployment", "router")
    container = router["spec"]["template"]["spec"]["containers"][0]
    assert container["args"] == ["router", "--listen", "tls/0.0.0.0:7447"]  # mutual TLS only
    config = service_config("router", environment(objs, router, container, 0), listen=("tls/0.0.0.0:7447",))
    assert config.bus.swarm == swarm_config(objs)["SWARMREC_SWARM"]
    gateway = find(objs, "Deployment", "gateway")
    container = gateway["spec"]["template"]["spec"]["containers"][0]
    config = service_config("gateway", environment(objs, gateway, container, 0))
    assert config.bus.connect == (f"tls/router.{namespace}.svc:7447",)
    assert config.bus.swarm == swarm_config(objs)["SWARMREC_SWARM"]
    assert (config.get(GatewaySettings).grpc_host, config.get(GatewaySettings).grpc_port) == (
        "0.0.0.0",
        50051,
    )
    assert {p["name"]: p["containerPort"] for p in container["ports"]} == {"grpc": 50051, "metrics": 9464}
    service = find(objs, "Service", "gateway")
    assert {p["name"]: p["port"] for p in service["spec"]["ports"]} == {"grpc": 50051, "metrics": 9464}


def test_the_robot_id_is_the_pods_statefulset_ordinal() -> None:
    for kind in ROBOT_KINDS:
        env = {v["name"]: v for v in service_container(find(rendered("local"), "StatefulSet", kind))["env"]}
        assert env["SWARMREC_ROBOT"]["valueFrom"]["fieldRef"]["fieldPath"] == (
            "metadata.labels['apps.kubernetes.io/pod-index']"
        )


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_container_runs_the_images_compose_runs_at_the_package_version(overlay: str) -> None:
    policy = {"local": "Never", "production": "IfNotPresent"}[overlay]
    for w in workloads(rendered(overlay)):
        for c in pod_containers(w):
            assert c["image"] in VERSIONED_IMAGES, (w["metadata"]["name"], c["name"], c["image"])
            assert c["imagePullPolicy"] == policy, (w["metadata"]["name"], c["name"])


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_service_runs_a_known_kind_and_is_probed_over_http_on_its_own_pages(overlay: str) -> None:
    for w in workloads(rendered(overlay)):
        name = w["metadata"]["name"]
        if name == "prometheus":
            continue
        container = w["spec"]["template"]["spec"]["containers"][0]
        assert container["args"][0] in registry.REGISTRY
        assert container["args"][0] == name  # the object is named after the kind it runs
        # The runner's own pages (swarmrec/runtime/metrics.py), no Python process per probe.
        paths = {"startupProbe": "/ready", "readinessProbe": "/ready", "livenessProbe": "/healthz"}
        for probe, path in paths.items():
            assert container[probe]["httpGet"] == {"path": path, "port": "metrics"}, (name, probe)
            assert "exec" not in container[probe]
        assert {"name": "metrics", "containerPort": 9464} in container["ports"]
        annotations = w["spec"]["template"]["metadata"]["annotations"]
        assert annotations == {
            "prometheus.io/scrape": "true",
            "prometheus.io/port": "9464",
            "prometheus.io/path": "/metrics",
        }


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_container_has_requests_and_a_memory_limit_and_runs_unprivileged(overlay: str) -> None:
    for w in workloads(rendered(overlay)):
        pod = w["spec"]["template"]["spec"]
        for c in pod_containers(w):
            where = (w["metadata"]["name"], c["name"])
            assert {"cpu", "memory"} <= set(c["resources"]["requests"]), where
            assert "memory" in c["resources"]["limits"], where
            assert c["securityContext"]["allowPrivilegeEscalation"] is False, where
            assert c["securityContext"]["capabilities"]["drop"] == ["ALL"], where
            # Only the local overlay's chown runs as root, with CAP_CHOWN alone.
            if c["name"] == "data-owner":
                assert overlay == "local" and c["securityContext"]["capabilities"]["add"] == ["CHOWN"]
            else:
                assert c["securityContext"].get("runAsNonRoot", pod["securityContext"]["runAsNonRoot"]), where


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_selectors_and_references_fit_together(overlay: str) -> None:
    objs = rendered(overlay)
    pod_labels = {w["metadata"]["name"]: w["spec"]["template"]["metadata"]["labels"] for w in workloads(objs)}

    def selects(selector: dict[str, str]) -> list[str]:
        return [n for n, labels in pod_labels.items() if selector.items() <= labels.items()]

    for w in workloads(objs):
        assert selects(w["spec"]["selector"]["matchLabels"]) == [w["metadata"]["name"]]
    for svc in (o for o in objs if o["kind"] == "Service"):
        assert selects(svc["spec"]["selector"]) == [svc["metadata"]["name"]]
        targets = {
            p["name"]
            for w in workloads(objs)
            if w["metadata"]["name"] == svc["metadata"]["name"]
            for c in w["spec"]["template"]["spec"]["containers"]
            for p in c.get("ports", [])
        }
        assert {p["targetPort"] for p in svc["spec"]["ports"]} <= targets
    for pdb in (o for o in objs if o["kind"] == "PodDisruptionBudget"):
        assert selects(pdb["spec"]["selector"]["matchLabels"]) == [pdb["metadata"]["name"]]
    for sts in (o for o in objs if o["kind"] == "StatefulSet"):
        assert find(objs, "Service", sts["spec"]["serviceName"])["spec"]["clusterIP"] == "None"
    config_maps = {o["metadata"]["name"] for o in objs if o["kind"] == "ConfigMap"}
    claims = {o["metadata"]["name"] for o in objs if o["kind"] == "PersistentVolumeClaim"}
    for w in workloads(objs):
        pod = w["spec"]["template"]["spec"]
        for c in pod_containers(w):
            refs = [e["configMapRef"]["name"] for e in c.get("envFrom", [])]
            refs += [
                v["valueFrom"]["configMapKeyRef"]["name"]
                for v in c.get("env", [])
                if "configMapKeyRef" in v.get("valueFrom", {})
            ]
            assert set(refs) <= config_maps, (w["metadata"]["name"], refs)
        for v in pod.get("volumes", []):
            if "configMap" in v:
                assert v["configMap"]["name"] in config_maps
            if "persistentVolumeClaim" in v:
                assert v["persistentVolumeClaim"]["claimName"] in claims
            # The Secrets are made by `swarmrec k8s secrets` (never committed, never rendered).
            for secret in _secrets_of(v):
                assert secret in secret_names(), (w["metadata"]["name"], secret)
    assert len({o["metadata"].get("namespace") for o in objs if o["kind"] != "Namespace"}) == 1


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_stateful_services_keep_their_records_on_a_volume_of_their_own(overlay: str) -> None:
    objs = rendered(overlay)
    for kind in ROBOT_KINDS:
        sts = find(objs, "StatefulSet", kind)
        mounts = {m["mountPath"]: m for m in service_container(sts).get("volumeMounts", [])}
        if kind not in STATEFUL_KINDS:
            assert "/var/lib/swarmrec" not in mounts
            continue
        mount = mounts["/var/lib/swarmrec"]
        if overlay == "local":
            # One folder per pod on the node, under the folder the cluster scripts name (and remove).
            assert "volumeClaimTemplates" not in sts["spec"]
            (volume,) = [v for v in sts["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"]]
            assert volume["hostPath"]["path"] == "/var/lib/swarmrec-k8s/volumes"
            assert mount["subPathExpr"] == "$(POD_NAMESPACE)/$(POD_NAME)"
            init = {
                m["mountPath"]: m
                for c in sts["spec"]["template"]["spec"]["initContainers"]
                for m in c["volumeMounts"]
            }
            assert init["/var/lib/swarmrec"]["subPathExpr"] == mount["subPathExpr"]
        else:
            (claim,) = sts["spec"]["volumeClaimTemplates"]
            assert claim["metadata"]["name"] == mount["name"]
            assert claim["spec"]["storageClassName"]
        assert sts["spec"]["persistentVolumeClaimRetentionPolicy"]["whenScaled"] == "Retain"


def test_the_local_volume_folder_is_the_default_the_cluster_scripts_use() -> None:
    env_sh = (REPO / "deploy/k8s/env.sh").read_text()
    assert "K8S_STATE=${SWARMREC_K8S_STATE:-/var/lib/swarmrec-k8s}" in env_sh
    assert "K8S_VOLUMES=$K8S_STATE/volumes" in env_sh


def test_production_spreads_each_kind_over_nodes_and_guarantees_its_memory() -> None:
    objs = rendered("production")
    for kind in ROBOT_KINDS:
        pod = find(objs, "StatefulSet", kind)["spec"]["template"]["spec"]
        keys = {c["topologyKey"] for c in pod["topologySpreadConstraints"]}
        assert keys == {"kubernetes.io/hostname", "topology.kubernetes.io/zone"}
        assert all(
            c["matchLabelKeys"] == ["app.kubernetes.io/component"] for c in pod["topologySpreadConstraints"]
        )
        anti = pod["affinity"]["podAntiAffinity"]["preferredDuringSchedulingIgnoredDuringExecution"]
        assert anti[0]["podAffinityTerm"]["matchLabelKeys"] == ["app.kubernetes.io/component"]
        resources = service_container(find(objs, "StatefulSet", kind))["resources"]
        assert resources["requests"]["memory"] == resources["limits"]["memory"]
    assert swarm_config(objs)["SWARMREC_LOCKSTEP"] == "false"
    assert {o["metadata"]["name"] for o in objs if o["kind"] == "PodDisruptionBudget"} == set(ROBOT_KINDS)


def test_prometheus_discovers_every_service_kind_and_labels_it_as_the_compose_targets() -> None:
    objs = rendered("local")
    (cm,) = [o for o in objs if o["kind"] == "ConfigMap" and o["metadata"]["name"].startswith("prometheus-")]
    config = cm["data"]["prometheus.yml"]
    # The labels the report reads (swarmrec/deployments/metrics.py): job swarmrec, service and robot.
    assert re.search(r"job_name: swarmrec\n", config)
    for label in ("service", "robot", "namespace", "pod"):
        assert f"target_label: {label}\n" in config
    # One SRV name per Service with a port named metrics: every kind the swarm runs.
    names = set(re.findall(r"- _metrics\._tcp\.([a-z-]+)\n", config))
    with_metrics = {
        o["metadata"]["name"]
        for o in objs
        if o["kind"] == "Service" and any(p["name"] == "metrics" for p in o["spec"]["ports"])
    }
    assert names == with_metrics == {"router", "gateway", *ROBOT_KINDS}
    for kind in ROBOT_KINDS:
        assert find(objs, "Service", kind)["spec"]["publishNotReadyAddresses"] is True


def test_the_hpa_example_scales_the_shard_statefulset_on_its_partial_query_rate() -> None:
    (hpa,) = yaml_to_objects((REPO / "k8s/examples/hpa-index-shard.yaml").read_text())
    assert hpa["spec"]["scaleTargetRef"] == {
        "apiVersion": "apps/v1",
        "kind": "StatefulSet",
        "name": "index-shard",
    }
    find(rendered("local"), "StatefulSet", "index-shard")
    (metric,) = hpa["spec"]["metrics"]
    assert metric["pods"]["metric"]["name"] == "swarmrec_shard_partial_queries_per_second"
    # It never scales past the shards the production swarm accepts (and has identities for), nor
    # below the replicas of a label group (fewer shards than robots is fine: groups are placed).
    from swarmrec.services.settings import IndexSettings

    config = swarm_config(rendered("production"))
    assert IndexSettings().replicas <= hpa["spec"]["minReplicas"]
    assert hpa["spec"]["maxReplicas"] <= int(config["SWARMREC_MAX_SHARDS"])


# --- scaling the index shards: ids past the robots, a grace period that outlasts the drain ------------


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_shard_statefulset_may_scale_to_max_shards_and_only_the_shards_go_past_the_robots(
    overlay: str,
) -> None:
    from swarmrec.deployments.kubernetes import max_shards_of
    from swarmrec.services.settings import IndexSettings

    objs = rendered(overlay)
    robots = int(swarm_config(objs)["SWARMREC_N_ROBOTS"])
    most = max_shards_of(objs)
    assert most == int(swarm_config(objs)["SWARMREC_MAX_SHARDS"]) > robots
    # The last ordinal the shard StatefulSet may be scaled to loads with the services' own loader.
    config = service_config("index-shard", robot_environment(objs, "index-shard", most - 1))
    assert (config.bus.robot, config.bus.n_robots, config.get(IndexSettings).max_shards) == (
        most - 1,
        robots,
        most,
    )
    # One past it is refused; the other kinds stay within the robots (their ids are robots).
    with pytest.raises(ConfigError, match=rf"robot must be in \[0, {most}\)"):
        service_config("index-shard", robot_environment(objs, "index-shard", most))
    for kind in ("verifier", "detector"):
        with pytest.raises(ConfigError, match=rf"robot must be in \[0, {robots}\)"):
            service_config(kind, robot_environment(objs, kind, robots))


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_index_shards_grace_period_outlasts_their_drain(overlay: str) -> None:
    from swarmrec.deployments.kubernetes import STOP_MARGIN_S
    from swarmrec.services.settings import IndexSettings

    objs = rendered(overlay)
    drain = service_config("index-shard", robot_environment(objs, "index-shard", 0)).get(IndexSettings)
    grace = {
        k: find(objs, "StatefulSet", k)["spec"]["template"]["spec"]["terminationGracePeriodSeconds"]
        for k in ROBOT_KINDS
    }
    assert grace["index-shard"] >= drain.drain_timeout_s + STOP_MARGIN_S
    assert {k: g for k, g in grace.items() if k != "index-shard"} == dict.fromkeys(ROBOT_KINDS[1:], 15)


def _ingress(acl: Obj, cn: str) -> set[tuple[str, str]]:
    """(message, key expression) an identity may send the router, from the router's acl.json."""
    rules = {r["id"]: r for r in acl["rules"]}
    (subject,) = [s["id"] for s in acl["subjects"] if cn in s.get("cert_common_names", [])]
    return {
        (m, k)
        for policy in acl["policies"]
        if subject in policy["subjects"]
        for rid in policy["rules"]
        if "ingress" in rules[rid]["flows"]
        for m in rules[rid]["messages"]
        for k in rules[rid]["key_exprs"]
    }


def test_identities_and_access_control_cover_every_shard_up_to_max_robots(tmp_path: Path) -> None:
    from swarmrec.deployments.kubernetes import kubernetes_pki, secret_objects

    folder = kubernetes_pki(tmp_path / "pki", "lab", 6, "ns")
    objs = {o["metadata"]["name"]: o for o in secret_objects(folder, "lab", 6, "ns")}
    assert {"r5.index-shard.lab.pem", "r5.index-shard.lab.key"} <= set(
        objs[secret_name("index-shard")]["data"]
    )
    acl = json.loads((folder / "acl.json").read_text())
    shard5 = _ingress(acl, "r5.index-shard.lab")
    assert ("declare_queryable", "swarmrec/v1/lab/index-shard/5/**") in shard5
    # Placements only as itself (the coordinator is whichever shard is lowest alive).
    assert ("query", "swarmrec/v1/lab/index-shard/*/adopt/5") in shard5
    assert ("liveliness_token", "swarmrec/v1/lab/alive/index-shard/5") in shard5
    # The descriptors of a 3-robot swarm reach every shard id; shard 5 reaches the others' transfer.
    assert {
        ("query", "swarmrec/v1/lab/index-shard/*/query/0"),
        ("query", "swarmrec/v1/lab/index-shard/*/store/0"),
    } <= _ingress(acl, "r0.descriptor.lab")
    assert ("query", "swarmrec/v1/lab/index-shard/*/transfer") in shard5


# --- identities: every pod its own, from Secrets no pod reads whole, none holding ca.key ---------------


def _secrets_of(volume: Obj) -> list[str]:
    """The Secrets a pod volume is made of (a secret volume, or a projected one)."""
    if "secret" in volume:
        return [volume["secret"]["secretName"]]
    return [
        src["secret"]["name"] for src in volume.get("projected", {}).get("sources", []) if "secret" in src
    ]


def swarm_workloads(objs: tuple[Obj, ...]) -> list[tuple[str, Obj]]:
    """(kind, workload) of every pod template that runs a swarm service."""
    out = [(k, find(objs, "Deployment", k)) for k in SWARM_KINDS]
    return out + [(k, find(objs, "StatefulSet", k)) for k in ROBOT_KINDS]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_only_the_identity_init_container_mounts_a_secret_and_read_only(overlay: str) -> None:
    for w in workloads(rendered(overlay)):
        pod = w["spec"]["template"]["spec"]
        secret_volumes = {v["name"] for v in pod.get("volumes", []) if _secrets_of(v)}
        if w["metadata"]["name"] == "prometheus":
            assert secret_volumes == set()
            continue
        assert len(secret_volumes) == 1, w["metadata"]["name"]
        for c in pod["containers"]:
            assert not secret_volumes & {m["name"] for m in c.get("volumeMounts", [])}, (w, c["name"])
        mounting = [
            (c["name"], m)
            for c in pod["initContainers"]
            for m in c["volumeMounts"]
            if m["name"] in secret_volumes
        ]
        assert [name for name, _ in mounting] == ["identity"]
        assert all(m["readOnly"] is True for _, m in mounting)
        # 0440: the pod's group (fsGroup, the services' uid) reads it, nobody else in the pod.
        (volume,) = [v for v in pod["volumes"] if v["name"] in secret_volumes]
        mode = volume.get("secret", volume.get("projected", {})).get("defaultMode")
        assert mode == 0o440 and pod["securityContext"]["fsGroup"] == 10001
        assert pod["automountServiceAccountToken"] is False


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_swarm_pod_presents_its_own_identity_from_its_kinds_secret(overlay: str) -> None:
    objs = rendered(overlay)
    for kind, w in swarm_workloads(objs):
        pod = w["spec"]["template"]["spec"]
        (init,) = [c for c in pod["initContainers"] if c["name"] == "identity"]
        service = pod["containers"][0]
        robot = 1 if w["kind"] == "StatefulSet" else 0
        init_env = environment(objs, w, init, robot)
        command = [re.sub(r"\$\((\w+)\)", lambda m, e=init_env: e[m.group(1)], a) for a in init["command"]]
        assert command == [
            "swarmrec",
            "k8s",
            "identity",
            "--kind",
            kind,
            "--from",
            "/run/swarmrec/secrets",
            "--to",
            PKI_DIR,
        ]
        # The same robot and swarm as the service: the copied pair is the one the service presents.
        service_env = environment(objs, w, service, robot)
        init_bus = load_config([BusSettings], env=init_env).bus
        service_bus = load_config([BusSettings], env=service_env).bus
        assert (
            (init_bus.swarm, init_bus.robot)
            == (service_bus.swarm, service_bus.robot)
            == (
                swarm_config(objs)["SWARMREC_SWARM"],
                robot,
            )
        )
        assert service_env["SWARMREC_PKI_DIR"] == PKI_DIR
        assert {"SWARMREC_SECURITY", "SWARMREC_IDENTITY"} & service_env.keys() == set()  # mtls, its kind's CN
        volumes = {v["name"]: v for v in pod["volumes"]}
        mounts = {m["mountPath"]: m for m in init["volumeMounts"]}
        expected = {secret_name(kind)} | ({"swarmrec-acl"} if kind == "router" else set())
        assert set(_secrets_of(volumes[mounts["/run/swarmrec/secrets"]["name"]])) == expected
        pki = volumes[mounts[PKI_DIR]["name"]]
        assert pki["emptyDir"]["medium"] == "Memory"  # never on the node's disk
        (service_mount,) = [m for m in service["volumeMounts"] if m["mountPath"] == PKI_DIR]
        assert service_mount == {"name": pki["name"], "mountPath": PKI_DIR, "readOnly": True}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_no_rendered_object_is_a_secret_or_names_the_ca_key(overlay: str) -> None:
    objs = rendered(overlay)
    assert [o["metadata"]["name"] for o in objs if o["kind"] == "Secret"] == []
    assert "ca.key" not in json.dumps(objs)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from swarmrec.deployments.kubernetes import kubernetes_pki

    folder = tmp_path_factory.mktemp("k8s-pki") / "pki"
    return kubernetes_pki(folder, "lab", 3, "ns", router_names=("10.96.0.10",), gateway_names=("10.96.0.11",))


def test_the_secrets_hold_each_kinds_pairs_and_never_the_ca_key(pki: Path) -> None:
    from swarmrec.deployments.kubernetes import secret_objects
    from swarmrec.security.certs import load_certificate, sans_of

    objs = {o["metadata"]["name"]: o for o in secret_objects(pki, "lab", 3, "ns")}
    assert sorted(objs) == sorted(secret_names())
    assert all(o["metadata"]["namespace"] == "ns" and o["type"] == "Opaque" for o in objs.values())
    keys = {name: set(o["data"]) for name, o in objs.items()}
    assert not any("ca.key" in k for k in keys.values())
    for kind in ROBOT_KINDS:
        pairs = {f"r{r}.{kind}.lab.{ext}" for r in range(3) for ext in ("pem", "key")}
        assert keys[secret_name(kind)] == {"ca.pem", *pairs}
    assert keys[secret_name("router")] == {"ca.pem", "router.lab.pem", "router.lab.key"}
    assert keys[secret_name("gateway")] == {"ca.pem", "client.gateway.lab.pem", "client.gateway.lab.key"}
    assert keys["swarmrec-acl"] == {"acl.json"}
    # Dialled by DNS name from the pods, by ClusterIP from the node.
    router = sans_of(load_certificate(pki / "router.lab.pem"))
    assert {"router.ns.svc", "router.ns.svc.cluster.local", "10.96.0.10"} <= router
    gateway = sans_of(load_certificate(pki / "client.gateway.lab.pem"))
    assert {"gateway.ns.svc", "10.96.0.11"} <= gateway


def test_a_router_certificate_lacking_a_new_service_address_is_reissued_and_nothing_else(
    tmp_path: Path,
) -> None:
    from swarmrec.deployments.kubernetes import kubernetes_pki
    from swarmrec.security.certs import load_certificate, sans_of

    folder = kubernetes_pki(tmp_path / "pki", "lab", 2, "ns", router_names=("10.96.0.10",))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    kubernetes_pki(folder, "lab", 2, "ns", router_names=("10.96.0.99",))
    after = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert "10.96.0.99" in sans_of(load_certificate(folder / "router.lab.pem"))
    changed = {n for n in before if before[n] != after[n]}
    assert changed == {"router.lab.pem", "router.lab.key"}


def _as_mounted(secret: Obj, folder: Path) -> Path:
    """A Secret's files as the kubelet mounts them with ``defaultMode: 0440`` and an fsGroup."""
    import base64

    folder.mkdir(parents=True)
    for name, value in secret["data"].items():
        (folder / name).write_bytes(base64.b64decode(value))
        os.chmod(folder / name, 0o440)
    return folder


def test_the_identity_copy_installs_the_pods_own_pair_only_and_the_service_accepts_it(
    pki: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from swarmrec.cli import main
    from swarmrec.deployments.kubernetes import secret_objects
    from swarmrec.runtime.tls import TlsFiles

    objs = {o["metadata"]["name"]: o for o in secret_objects(pki, "lab", 3, "ns")}
    mounted = _as_mounted(objs[secret_name("index-shard")], tmp_path / "secrets")
    target = tmp_path / "pki"
    # What robot 2's shard pod's init container runs (its variables from the pod's env).
    for name, value in {"SWARMREC_ROBOT": "2", "SWARMREC_SWARM": "lab", "SWARMREC_N_ROBOTS": "3"}.items():
        monkeypatch.setenv(name, value)
    argv = ["k8s", "identity", "--kind", "index-shard", "--from", str(mounted), "--to", str(target)]
    assert main(argv) == 0
    assert sorted(p.name for p in target.iterdir()) == [
        "ca.pem",
        "r2.index-shard.lab.key",
        "r2.index-shard.lab.pem",
    ]
    assert (target / "r2.index-shard.lab.key").stat().st_mode & 0o777 == 0o600
    TlsFiles.in_dir(target, "r2.index-shard.lab").check()  # what the runner checks before zenoh reads them
    # The router's copy takes its access control too (its volume projects two Secrets).
    router = _as_mounted(objs[secret_name("router")], tmp_path / "router")
    (router / "acl.json").write_bytes((pki / "acl.json").read_bytes())
    assert (
        main(["k8s", "identity", "--kind", "router", "--from", str(router), "--to", str(tmp_path / "r")]) == 0
    )
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == [
        "acl.json",
        "ca.pem",
        "router.lab.key",
        "router.lab.pem",
    ]


def test_the_identity_copy_installs_a_shard_past_the_robots_up_to_max_shards_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from swarmrec.cli import main
    from swarmrec.deployments.kubernetes import kubernetes_pki, secret_objects

    folder = kubernetes_pki(tmp_path / "pki", "lab", 6, "ns")
    objs = {o["metadata"]["name"]: o for o in secret_objects(folder, "lab", 6, "ns")}
    # A shard StatefulSet of a 3-robot swarm scaled to 6: pod index-shard-5's init container.
    env = {
        "SWARMREC_ROBOT": "5",
        "SWARMREC_SWARM": "lab",
        "SWARMREC_N_ROBOTS": "3",
        "SWARMREC_MAX_SHARDS": "6",
    }
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    shards = _as_mounted(objs[secret_name("index-shard")], tmp_path / "shards")
    argv = ["k8s", "identity", "--kind", "index-shard", "--from", str(shards), "--to", str(tmp_path / "s5")]
    assert main(argv) == 0
    assert sorted(p.name for p in (tmp_path / "s5").iterdir()) == [
        "ca.pem",
        "r5.index-shard.lab.key",
        "r5.index-shard.lab.pem",
    ]
    # A verifier's ids are robots: robot 5 of 3 is refused, though its Secret holds the pair.
    verifiers = _as_mounted(objs[secret_name("verifier")], tmp_path / "verifiers")
    argv = ["k8s", "identity", "--kind", "verifier", "--from", str(verifiers), "--to", str(tmp_path / "v5")]
    assert main(argv) != 0
    assert not (tmp_path / "v5").exists()


def test_the_identity_copy_refuses_a_missing_or_foreign_pair(pki: Path, tmp_path: Path) -> None:
    from swarmrec.deployments.kubernetes import kubernetes_pki, secret_objects
    from swarmrec.errors import SecurityError
    from swarmrec.security.install import install_identity

    objs = {o["metadata"]["name"]: o for o in secret_objects(pki, "lab", 3, "ns")}
    mounted = _as_mounted(objs[secret_name("verifier")], tmp_path / "secrets")
    with pytest.raises(SecurityError, match="max-robots"):  # robot 5 of a PKI made for 3
        install_identity(mounted, tmp_path / "out", "r5.verifier.lab")
    # Robot 1's pair under robot 0's name; then a pair of another swarm CA.
    (mounted / "r0.verifier.lab.pem").chmod(0o640)
    (mounted / "r0.verifier.lab.pem").write_bytes((mounted / "r1.verifier.lab.pem").read_bytes())
    with pytest.raises(SecurityError, match=re.escape("is for 'r1.verifier.lab'")):
        install_identity(mounted, tmp_path / "out", "r0.verifier.lab")
    other = kubernetes_pki(tmp_path / "other", "lab", 3, "ns")
    (mounted / "r2.verifier.lab.pem").chmod(0o640)
    (mounted / "r2.verifier.lab.pem").write_bytes((other / "r2.verifier.lab.pem").read_bytes())
    with pytest.raises(SecurityError, match="was not issued by"):
        install_identity(mounted, tmp_path / "out", "r2.verifier.lab")
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []


# --- the overlay KubernetesDeployment renders for a run ---------------------------------------------


def test_a_runs_overlay_sets_the_specs_robots_settings_and_dataset(tmp_path: Path) -> None:
    import zipfile

    from swarmrec.datasets.constellations import read_constellations
    from swarmrec.datasets.labels import label_names
    from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, shared_env, write_overlay
    from swarmrec.evaluation.source import DatasetSource
    from swarmrec.experiments.places.pipeline import prepare
    from swarmrec.experiments.places.settings import PlacesSettings

    run = PlacesSettings(source=DatasetSource(frames=60), robots=2, swarm="lab", out=tmp_path)
    spec = prepare(run, dataset_dir=tmp_path / "dataset").spec
    folder = write_overlay(spec, "run-ns", DEFAULT_OVERLAY, tmp_path / "overlay")
    ensure_kubectl()
    objs = tuple(yaml_to_objects(kubectl_run("kustomize", str(folder))))
    assert [e for o in objs for e in validate(o)] == []
    assert {o["metadata"].get("namespace") for o in objs if o["kind"] != "Namespace"} == {"run-ns"}
    assert {k: find(objs, "StatefulSet", k)["spec"]["replicas"] for k in ROBOT_KINDS} == dict.fromkeys(
        ROBOT_KINDS, 2
    )
    # Every robot service loads the spec's own place-recognition settings from the ConfigMap.
    wanted = spec.component(PlaceSettings)
    for kind in ("index-shard", "verifier", "descriptor"):
        for robot in (0, 1):
            config = service_config(kind, robot_environment(objs, kind, robot))
            assert (
                config.get(PlaceSettings) == wanted and config.bus.n_robots == 2 and config.bus.robot == robot
            )
    assert set(shared_env(spec)) <= set(swarm_config(objs))
    # A deployment with certificates for 5 robots: its shards accept ids up to 4; their grace
    # period follows the run's drain timeout.
    from swarmrec.deployments.kubernetes import STOP_MARGIN_S, cluster_spec
    from swarmrec.services.settings import IndexSettings

    scaled = prepare(
        run.with_(index=IndexSettings(drain_timeout_s=90.0)), dataset_dir=tmp_path / "dataset"
    ).spec
    folder = write_overlay(cluster_spec(scaled, 5), "run-ns", DEFAULT_OVERLAY, tmp_path / "scaled")
    more = tuple(yaml_to_objects(kubectl_run("kustomize", str(folder))))
    assert swarm_config(more)["SWARMREC_MAX_SHARDS"] == "5" and swarm_config(more)["SWARMREC_N_ROBOTS"] == "2"
    shard4 = service_config("index-shard", robot_environment(more, "index-shard", 4))
    assert (shard4.bus.robot, shard4.get(IndexSettings).drain_timeout_s) == (4, 90.0)
    pod = find(more, "StatefulSet", "index-shard")["spec"]["template"]["spec"]
    assert pod["terminationGracePeriodSeconds"] == 90 + STOP_MARGIN_S
    assert not {"SWARMREC_ROBOT", "SWARMREC_CONNECT", "SWARMREC_PKI_DIR", "SWARMREC_DATASET"} & set(
        swarm_config(objs)
    )
    # The detectors replay the run's own frames, from a ConfigMap, not a world of their own.
    detector = find(objs, "StatefulSet", "detector")
    pod = detector["spec"]["template"]["spec"]
    assert [c["name"] for c in pod["initContainers"]] == ["identity"]
    (volume,) = [v for v in pod["volumes"] if v["name"] == "dataset"]
    assert set(volume) == {"name", "configMap"}
    data = find(objs, "ConfigMap", volume["configMap"]["name"])["binaryData"]["dataset.zip"]
    config = service_config("detector", robot_environment(objs, "detector", 0))
    assert config.get(DetectorSettings).dataset == "/data/dataset.zip"
    import base64
    import io

    (tmp_path / "in-pod.zip").write_bytes(base64.b64decode(data))
    with zipfile.ZipFile(io.BytesIO(base64.b64decode(data))) as z:
        assert z.testzip() is None
    seq = read_constellations(tmp_path / "in-pod.zip", label_names())
    assert seq.frame_ids == read_constellations(tmp_path / "dataset", label_names()).frame_ids
