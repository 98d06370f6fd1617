"""Why a workload's pods are not ready, in a few lines a user can act on.

``kubectl rollout status`` says only "timed out waiting for the condition". When a rollout
does not finish, the deployment reads the workload's pods (``kubectl get pods -o json``) and
the namespace's warning events, and says per pod what holds it: Pending and why the
scheduler left it there, a container waiting (CrashLoopBackOff, ImagePullBackOff) or killed
(OOMKilled, an exit code), restarts, a failing readiness probe.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["not_ready_containers", "not_ready_report", "selector_of"]

#: Lines of a report at most: a workload of many pods says the first ones' reasons.
MAX_LINES = 30


def selector_of(workload: Mapping[str, Any]) -> str:
    """A workload object's ``spec.selector.matchLabels`` as a ``kubectl -l`` selector."""
    labels = workload.get("spec", {}).get("selector", {}).get("matchLabels", {})
    return ",".join(f"{k}={v}" for k, v in sorted(labels.items()))


def _by_name(items: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    return sorted(items, key=lambda p: str(p.get("metadata", {}).get("name", "")))


def _statuses(pod: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    """A pod's init containers' statuses, then its containers'."""
    status = pod.get("status", {})
    return [*status.get("initContainerStatuses", []), *status.get("containerStatuses", [])]


def _completed(status: Mapping[str, Any]) -> bool:
    """An init container that ran to its end: done, not trouble."""
    return int(status.get("state", {}).get("terminated", {}).get("exitCode", -1)) == 0


def _container_lines(status: Mapping[str, Any]) -> list[str]:
    name = status.get("name", "?")
    if _completed(status):
        return []
    out = []
    state = status.get("state", {})
    if "waiting" in state:
        w = state["waiting"]
        out.append(f"{name} waiting: {w.get('reason', '?')} {w.get('message', '')}".rstrip())
    elif "terminated" in state:
        t = state["terminated"]
        out.append(f"{name} terminated: {t.get('reason', '?')} (exit {t.get('exitCode', '?')})")
    elif "running" in state and not status.get("ready", False):
        out.append(f"{name} running, not ready")
    last = status.get("lastState", {}).get("terminated")
    restarts = int(status.get("restartCount", 0))
    if restarts:
        why = f", last {last.get('reason', '?')} (exit {last.get('exitCode', '?')})" if last else ""
        out.append(f"{name} restarted {restarts} times{why}")
    return out


def _pod_lines(pod: Mapping[str, Any]) -> list[str]:
    status = pod.get("status", {})
    phase = status.get("phase", "?")
    lines: list[str] = []
    for cond in status.get("conditions", []):
        if cond.get("type") == "PodScheduled" and cond.get("status") != "True":
            lines.append(f"not scheduled: {cond.get('reason', '?')} {cond.get('message', '')}".rstrip())
    for c in _statuses(pod):
        lines.extend(_container_lines(c))
    ready = any(c.get("type") == "Ready" and c.get("status") == "True" for c in status.get("conditions", []))
    if ready and not lines:
        return []
    return [f"{phase}{'' if ready else ', not ready'}", *lines]


def not_ready_containers(pods: Mapping[str, Any], limit: int = 3) -> list[tuple[str, str, bool]]:
    """(pod, container, whether it restarted) of the first ``limit`` containers that started
    and are not ready: their logs say what the pod status cannot (a service stuck starting)."""
    out: list[tuple[str, str, bool]] = []
    for pod in _by_name(pods.get("items", [])):
        name = pod.get("metadata", {}).get("name", "?")
        for c in _statuses(pod):
            restarted = int(c.get("restartCount", 0)) > 0
            started = "running" in c.get("state", {}) or "terminated" in c.get("state", {}) or restarted
            if started and not c.get("ready", False) and not _completed(c):
                out.append((name, c.get("name", "?"), restarted))
                if len(out) == limit:
                    return out
    return out


def not_ready_report(pods: Mapping[str, Any], events: Mapping[str, Any] | None = None) -> str:
    """What holds each pod of ``pods`` (a ``kubectl get pods -o json`` List) from ready,
    with each pod's newest warning events from ``events`` (``kubectl get events -o json``).
    Pods that are ready are left out; an empty List says so."""
    items: Sequence[Mapping[str, Any]] = pods.get("items", [])
    if not items:
        return "no pod of the workload exists (see the controller's events: kubectl describe)"
    warnings: dict[str, list[str]] = {}
    for ev in (events or {}).get("items", []):
        obj = ev.get("involvedObject", {})
        if ev.get("type") == "Warning" and obj.get("kind") == "Pod":
            count = int(ev.get("count") or 1)
            text = f"event {ev.get('reason', '?')}: {ev.get('message', '').strip()}"
            warnings.setdefault(obj.get("name", ""), []).append(text + (f" (x{count})" if count > 1 else ""))
    out: list[str] = []
    for pod in _by_name(items):
        name = pod.get("metadata", {}).get("name", "?")
        lines = _pod_lines(pod)
        if not lines:
            continue
        out.append(f"pod {name}: {lines[0]}")
        out.extend(f"  {line}" for line in lines[1:])
        out.extend(f"  {w}" for w in warnings.get(name, [])[-3:])
    if not out:
        return "every pod of the workload is ready"
    if len(out) > MAX_LINES:
        out = [*out[:MAX_LINES], f"... {len(out) - MAX_LINES} more lines"]
    return "\n".join(out)
