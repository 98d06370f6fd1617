"""The shape of the package: layers respected, no import cycle, public surfaces true,
every catchable error in the tree, README's layout table true to the tree."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import swarmrec
from swarmrec import errors
from swarmrec.errors import SwarmrecError
from swarmrec.layers import CORE_BANDS, LAYERS, band_of, cycles, import_graph, layer_of, upward_imports
from tests.conftest import REPO

GRAPH = import_graph()


def test_the_package_has_no_import_cycle_counting_imports_inside_functions() -> None:
    assert cycles(GRAPH) == []


def test_no_module_imports_a_higher_layer() -> None:
    assert upward_imports(GRAPH) == []


def test_every_module_is_in_a_layer() -> None:
    for module in GRAPH:
        layer_of(module)  # raises for a module no layer names


PIPELINES = [f"swarmrec.experiments.{m}.pipeline" for m in ("places", "vpr", "slam", "landmarks")]
DEPLOYMENT_KINDS = {f"swarmrec.deployments.{m}" for m in ("local", "local_up", "compose", "kubernetes")}


@pytest.mark.parametrize("pipeline", PIPELINES)
def test_a_pipeline_knows_no_kind_of_deployment_and_never_asks_which_it_has(pipeline: str) -> None:
    # It is handed its deployment (the command line builds it) and asks the protocol the rest.
    assert GRAPH[pipeline] & DEPLOYMENT_KINDS == set()
    source = (REPO / (pipeline.replace(".", "/") + ".py")).read_text()
    assert re.search(r"isinstance\(deployment", source) is None
    assert re.search(r"deployment: Deployment \| None", source) is None


def test_the_checks_catch_what_they_are_for() -> None:
    # A wire module importing the runner is upward; two modules importing each other are a cycle.
    bad = dict(GRAPH)
    bad["swarmrec.wire.codec"] = GRAPH["swarmrec.wire.codec"] | {"swarmrec.runtime.runner"}
    assert ("swarmrec.wire.codec", "swarmrec.runtime.runner") in upward_imports(bad)
    bad["swarmrec.runtime.runner"] = GRAPH["swarmrec.runtime.runner"] | {"swarmrec.wire.codec"}
    assert any({"swarmrec.wire.codec", "swarmrec.runtime.runner"} <= set(c) for c in cycles(bad))


def test_the_core_bands_hold_every_core_package_once_and_the_check_sees_an_import_up_a_band() -> None:
    core = dict(LAYERS)["core"]
    banded = [p for band in CORE_BANDS for p in band]
    assert sorted(banded) == sorted(core)
    assert all(band_of(m) >= 0 for m in GRAPH if layer_of(m) == 0)
    # The datasets reading the synthetic world is up a band (it was so before evaluation.source).
    bad = dict(GRAPH)
    bad["swarmrec.datasets.constellations"] = GRAPH["swarmrec.datasets.constellations"] | {
        "swarmrec.synthetic"
    }
    assert ("swarmrec.datasets.constellations", "swarmrec.synthetic") in upward_imports(bad)


def test_the_layers_named_in_the_architecture_page_are_the_packages() -> None:
    text = (REPO / "docs" / "architecture.md").read_text()
    for name, _prefixes in LAYERS:
        assert f"**{name}**" in text, name


def _modules() -> list[str]:
    return sorted(
        m.name
        for m in pkgutil.walk_packages(swarmrec.__path__, "swarmrec.")
        if ".gen" not in m.name and not m.name.endswith("__main__")
    )


@pytest.mark.parametrize("name", _modules())
def test_a_modules_all_names_only_what_it_defines(name: str) -> None:
    module = importlib.import_module(name)
    for public in getattr(module, "__all__", []):
        assert hasattr(module, public), f"{name}.__all__ names {public}, which it does not have"


def _subclasses(cls: type) -> set[type]:
    out = set()
    for sub in cls.__subclasses__():
        out |= {sub} | _subclasses(sub)
    return out


def test_every_error_a_user_can_catch_is_in_the_tree_of_errors_py() -> None:
    for name in _modules():
        importlib.import_module(name)
    tree = errors.__doc__ or ""
    missing = [
        f"{c.__module__}.{c.__name__}"
        for c in _subclasses(SwarmrecError)
        if c.__module__.startswith("swarmrec") and not re.search(rf"\b{c.__name__}\b", tree)
    ]
    assert missing == []


def test_the_error_codes_are_the_schemas() -> None:
    from swarmrec.wire import messages as pb

    assert {c.wire_name: int(c) for c in errors.ErrorCode} == dict(pb.ErrorCode.items())


def test_readmes_layout_table_names_paths_that_exist_and_every_top_level_folder() -> None:
    text = (REPO / "README.md").read_text()
    section = text.split("## What is here", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| (`[^|]+`) \|", section, re.MULTILINE)
    paths = [p for row in rows for p in re.findall(r"`([^`]+)`", row)]
    assert paths, "README has no layout table"
    for path in paths:
        assert (REPO / path.rstrip("/")).exists(), path
    named = {p.split("/")[0] for p in paths}
    folders = {
        p.name
        for p in REPO.iterdir()
        if p.is_dir()
        and not p.name.startswith(".")
        and p.name not in ("runs", "build", "dist", "target", "__pycache__", "swarmrec.egg-info")
    }
    assert folders <= named | {"swarmrec"}, folders - named
    subpackages = {
        p.name for p in (REPO / "swarmrec").iterdir() if p.is_dir() and (p / "__init__.py").exists()
    }
    described = {p.split("/")[1] for p in paths if p.startswith("swarmrec/") and p.count("/") >= 1}
    assert subpackages <= described, subpackages - described


def test_the_layers_module_names_its_own_layer_table_in_its_docstring() -> None:
    tree = ast.parse(Path(importlib.import_module("swarmrec.layers").__file__ or "").read_text())
    doc = ast.get_docstring(tree) or ""
    for name, _prefixes in LAYERS:
        assert re.search(rf"^\s+{name}\s", doc, re.MULTILINE), name
