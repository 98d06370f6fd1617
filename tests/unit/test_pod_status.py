"""What a timed-out rollout says about its pods (swarmrec.deployments.pod_status)."""

from __future__ import annotations

from typing import Any

from swarmrec.deployments.pod_status import MAX_LINES, not_ready_containers, not_ready_report, selector_of


def _pod(
    name: str, phase: str, ready: bool, containers: list[dict[str, Any]], **extra: Any
) -> dict[str, Any]:
    conditions = [{"type": "Ready", "status": "True" if ready else "False"}, *extra.get("conditions", [])]
    return {
        "metadata": {"name": name},
        "status": {"phase": phase, "conditions": conditions, "containerStatuses": containers},
    }


def test_the_selector_is_the_workloads_match_labels_sorted() -> None:
    workload = {"spec": {"selector": {"matchLabels": {"robot-kind": "detector", "app": "swarmrec"}}}}
    assert selector_of(workload) == "app=swarmrec,robot-kind=detector"


def test_a_crash_looping_container_says_why_it_last_died_and_its_events() -> None:
    crashing = {
        "name": "detector",
        "ready": False,
        "restartCount": 4,
        "state": {"waiting": {"reason": "CrashLoopBackOff", "message": "back-off 1m20s"}},
        "lastState": {"terminated": {"reason": "OOMKilled", "exitCode": 137}},
    }
    pods = {"items": [_pod("detector-1", "Running", False, [crashing])]}
    events = {
        "items": [
            {
                "type": "Warning",
                "reason": "BackOff",
                "message": "Back-off restarting failed container",
                "count": 7,
                "involvedObject": {"kind": "Pod", "name": "detector-1"},
            },
            {  # a normal event and another pod's warning are not this pod's trouble
                "type": "Normal",
                "reason": "Pulled",
                "message": "image present",
                "involvedObject": {"kind": "Pod", "name": "detector-1"},
            },
            {
                "type": "Warning",
                "reason": "BackOff",
                "message": "elsewhere",
                "involvedObject": {"kind": "Pod", "name": "router-0"},
            },
        ]
    }
    assert not_ready_report(pods, events).splitlines() == [
        "pod detector-1: Running, not ready",
        "  detector waiting: CrashLoopBackOff back-off 1m20s",
        "  detector restarted 4 times, last OOMKilled (exit 137)",
        "  event BackOff: Back-off restarting failed container (x7)",
    ]


def test_an_unscheduled_pod_says_what_the_scheduler_said_and_ready_pods_are_left_out() -> None:
    running = {"name": "detector", "ready": True, "restartCount": 0, "state": {"running": {}}}
    unscheduled = {
        "type": "PodScheduled",
        "status": "False",
        "reason": "Unschedulable",
        "message": "0/1 nodes are available: 1 Insufficient cpu.",
    }
    pods = {
        "items": [
            _pod("detector-0", "Running", True, [running]),
            _pod("detector-2", "Pending", False, [], conditions=[unscheduled]),
        ]
    }
    assert not_ready_report(pods).splitlines() == [
        "pod detector-2: Pending, not ready",
        "  not scheduled: Unschedulable 0/1 nodes are available: 1 Insufficient cpu.",
    ]


def test_a_running_container_failing_its_probe_and_a_workload_without_pods() -> None:
    probing = {"name": "index-shard", "ready": False, "restartCount": 0, "state": {"running": {}}}
    pods = {"items": [_pod("index-shard-0", "Running", False, [probing])]}
    # An init container that completed is no trouble: neither said nor its log read.
    done = {
        "name": "identity",
        "ready": False,
        "state": {"terminated": {"reason": "Completed", "exitCode": 0}},
    }
    pods["items"][0]["status"]["initContainerStatuses"] = [done]
    assert not_ready_containers(pods) == [("index-shard-0", "index-shard", False)]
    assert not_ready_report(pods).splitlines() == [
        "pod index-shard-0: Running, not ready",
        "  index-shard running, not ready",
    ]
    assert not_ready_report({"items": []}).startswith("no pod of the workload exists")
    running = {"name": "x", "ready": True, "restartCount": 0, "state": {"running": {}}}
    assert not_ready_report({"items": [_pod("x-0", "Running", True, [running])]}) == (
        "every pod of the workload is ready"
    )


def test_a_report_of_many_pods_is_cut_at_max_lines() -> None:
    waiting = {"name": "c", "ready": False, "state": {"waiting": {"reason": "ImagePullBackOff"}}}
    pods = {"items": [_pod(f"p-{i:03d}", "Pending", False, [waiting]) for i in range(100)]}
    lines = not_ready_report(pods).splitlines()
    assert len(lines) == MAX_LINES + 1
    assert lines[0] == "pod p-000: Pending, not ready"
    assert lines[1] == "  c waiting: ImagePullBackOff"
    assert lines[-1] == f"... {200 - MAX_LINES} more lines"


def test_the_containers_whose_logs_are_read_are_those_started_and_not_ready() -> None:
    running_ready = {"name": "a", "ready": True, "state": {"running": {}}}
    running_not_ready = {"name": "b", "ready": False, "state": {"running": {}}}
    never_started = {"name": "c", "ready": False, "state": {"waiting": {"reason": "ContainerCreating"}}}
    crashed = {
        "name": "d",
        "ready": False,
        "restartCount": 2,
        "state": {"waiting": {"reason": "CrashLoopBackOff"}},
    }
    pods = {
        "items": [
            _pod("p-1", "Running", False, [running_ready, running_not_ready]),
            _pod("p-0", "Running", False, [never_started, crashed]),
        ]
    }
    assert not_ready_containers(pods) == [("p-0", "d", True), ("p-1", "b", False)]
    assert not_ready_containers(pods, limit=1) == [("p-0", "d", True)]
