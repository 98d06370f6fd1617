"""The CPU accounting of bench/bench_cpu.py: thread classes read from /proc, and the
per-query arithmetic."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest
import zenoh

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_cpu.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_cpu", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_cpu"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def test_zenohs_runtime_threads_are_told_from_python_threads(bench: ModuleType) -> None:
    before = bench.read_threads(os.getpid())
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf):
        during = bench.read_threads(os.getpid())
    assert "python" in before.switches
    # zenoh names its runtime's threads (tx-0, net-0, ...): a session starts some.
    assert "zenoh_runtime" in during.switches
    assert during.cpu[("python", "user")] >= before.cpu[("python", "user")]


@pytest.mark.parametrize(
    ("name", "role"),
    [
        ("host-r0-4", "robot hosts"),
        ("router-0", "router"),
        ("gateway-0", "gateway"),
        ("index-shard-3", "index-shard"),
        # The compiled host a `swarmrec host` starts, counted as its parent's child.
        ("host-r0-4/swarmrec-dataplane-4242", "robot hosts (swarmrec-dataplane)"),
    ],
)
def test_a_process_is_named_by_its_role(bench: ModuleType, name: str, role: str) -> None:
    assert bench.process_role(name) == role


def test_cpu_and_switches_are_divided_by_the_queries_between_the_two_looks(bench: ModuleType) -> None:
    t = bench.Threads
    before = {
        "host-r0-4": t({("python", "user"): 1.0, ("zenoh_runtime", "kernel"): 0.5}, {"python": 100}),
        "router": t({("zenoh_runtime", "user"): 0.2}, {"zenoh_runtime": 10}),
    }
    after = {
        "host-r0-4": t({("python", "user"): 3.0, ("zenoh_runtime", "kernel"): 1.5}, {"python": 300}),
        "router": t({("zenoh_runtime", "user"): 1.2}, {"zenoh_runtime": 50}),
        "replay driver (this process)": t({("python", "user"): 0.5}, {"python": 20}),  # new: all counted
    }
    acc = bench.account(before, after, queries=1000)
    assert acc["cpu_s"] == pytest.approx(2.0 + 1.0 + 1.0 + 0.5)
    assert acc["cpu_ms_per_query"] == pytest.approx(4.5)
    assert acc["cpu_ms_per_query_by_process"] == pytest.approx(
        {"robot hosts": 3.0, "router": 1.0, "replay driver": 0.5}
    )
    assert acc["cpu_ms_per_query_by_thread"] == pytest.approx({"python": 2.5, "zenoh_runtime": 2.0})
    assert acc["cpu_ms_per_query_user_kernel"] == pytest.approx({"user": 3.5, "kernel": 1.0})
    assert acc["context_switches_per_query"] == pytest.approx({"python": 0.22, "zenoh_runtime": 0.04})


def test_every_process_under_a_host_is_found_nearest_first(bench: ModuleType) -> None:
    # 10 -> 11 -> 13, 10 -> 12; 20 is another tree.
    parents = {10: 1, 11: 10, 12: 10, 13: 11, 20: 1}
    assert bench.descendants(parents, 10) == [11, 12, 13]
    assert bench.descendants(parents, 20) == []


def test_a_childs_cost_is_added_to_its_parents_role_and_runs_compare_as_ratios(bench: ModuleType) -> None:
    by_role = {"robot hosts": 7.5, "robot hosts (swarmrec-dataplane)": 0.5, "router": 1.0}
    assert bench.with_children(by_role) == {"robot hosts": 8.0, "router": 1.0}
    assert bench.ratio(2.0, 0.0) is None and bench.ratio(None, 1.0) is None and bench.ratio(3.0, 2.0) == 1.5

    def run(cpu: float, hosts: float, child: float | None) -> dict[str, object]:
        roles = {"robot hosts": hosts} | ({"robot hosts (swarmrec-dataplane)": child} if child else {})
        return {
            "cpu_ms_per_query": cpu,
            "context_switches_per_query": {"python": 100.0},
            "cpu_ms_per_query_by_process": roles,
            "cpu_ms_per_query_by_thread": {"python": cpu},
            "cpu_ms_per_query_user_kernel": {"user": cpu},
            "window_s": 10.0,
            "timings": {"replay_s": 5.0},
        }

    ratios = bench.compare(run(10.0, 10.0, None), run(8.0, 6.0, 2.0))
    assert ratios["cpu_ms_per_query"] == 1.25 and ratios["cpu_ms_saved_per_query"] == 2.0
    assert ratios["cpu_ms_per_query_by_process"]["robot hosts (swarmrec-dataplane)"] is None
    assert ratios["cpu_ms_per_query_by_process_with_children"] == {"robot hosts": 1.25}
