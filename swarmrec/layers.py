"""The package's layers, and the import graph that must respect them.

Lowest first; a module may import modules of its own layer or of lower ones, never
of a higher one, and no two modules may import each other, even through others
(every import statement counts, also one inside a function)::

    core         pure libraries: constellations, fusion, datasets, the synthetic world,
                 detection, evaluation, SLAM back ends, errors, model lookup and loading (no bus)
    wire         the v1 protobuf messages and the codec to and from the core's types
    runtime      the bus plumbing: settings per component, keys, request/response,
                 metrics, record logs, TLS, the runner
    services     the registry and each service kind; the client library and the
                 two-step query it shares with the descriptor service
    deployments  where a swarm runs (local processes, compose) and its PKI
    experiments  pipelines that take a deployment (places, landmarks, slam)
    cli          the ``swarmrec`` command line

The core layer is ordered too, in bands (:data:`CORE_BANDS`, lowest first)::

    errors < core < models, inference < datasets < slam < fusion < synthetic
           < detection < evaluation < vpr

so that two core packages never import each other (the data an evaluation runs on,
a named dataset or the synthetic world, is the evaluation's: ``evaluation.source``).

``python -m swarmrec.layers`` prints the graph's counts between layers and any
violation; ``--figure PATH`` draws the picture in docs/architecture.md.
tests/unit/test_architecture.py fails on a cycle or an upward import.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from collections.abc import Iterator, Mapping
from pathlib import Path

__all__ = ["CORE_BANDS", "LAYERS", "band_of", "cycles", "import_graph", "layer_of", "main", "upward_imports"]

#: (layer, the module prefixes in it), lowest first.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "core",
        (
            "swarmrec.core",
            "swarmrec.fusion",
            "swarmrec.datasets",
            "swarmrec.synthetic",
            "swarmrec.detection",
            "swarmrec.evaluation",
            "swarmrec.errors",
            "swarmrec.models",
            "swarmrec.inference",
            "swarmrec.slam",
            "swarmrec.vpr",
        ),
    ),
    ("wire", ("swarmrec.wire",)),
    ("runtime", ("swarmrec.runtime",)),
    ("services", ("swarmrec.services", "swarmrec.client", "swarmrec.healthcheck")),
    ("deployments", ("swarmrec.deployments", "swarmrec.security")),
    ("experiments", ("swarmrec.experiments",)),
    ("cli", ("swarmrec.cli", "swarmrec.__main__", "swarmrec.layers")),
)

#: The core layer's packages in bands, lowest first: a core module imports its own band
#: or lower ones. Every package of the core layer is in one.
CORE_BANDS: tuple[tuple[str, ...], ...] = (
    ("swarmrec.errors",),
    ("swarmrec.core",),
    ("swarmrec.models", "swarmrec.inference"),
    ("swarmrec.datasets",),
    ("swarmrec.slam",),
    ("swarmrec.fusion",),
    ("swarmrec.synthetic",),
    ("swarmrec.detection",),
    ("swarmrec.evaluation",),
    ("swarmrec.vpr",),
)

PACKAGE = Path(__file__).resolve().parent


def layer_of(module: str) -> int:
    """The index in :data:`LAYERS` of ``module``'s layer; -1 for the package itself."""
    if module == "swarmrec":
        return -1
    for i, (_name, prefixes) in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    raise KeyError(f"{module} is in no layer of swarmrec.layers.LAYERS")


def band_of(module: str) -> int:
    """The index in :data:`CORE_BANDS` of a core module's band; -1 outside the core layer."""
    for i, prefixes in enumerate(CORE_BANDS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    return -1


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        if "gen" in rel.parts:  # generated protobuf code: it imports only protobuf
            continue
        name = ".".join(rel.parts).removesuffix(".__init__")
        out[name] = path
    return out


def _imported(module: str, path: Path, known: Mapping[str, Path]) -> Iterator[str]:
    """The package modules ``module`` imports, every statement (also inside functions)."""
    base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = node.module or ""
            if node.level:
                target = ".".join(base[: len(base) - node.level + 1] + ([target] if target else []))
            names = [target] + [f"{target}.{a.name}" for a in node.names]
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if not name or name == module:
                continue
            # A package's __init__ runs before any of its modules; importing it counts only
            # from outside the package (as the before-stop hook's checker counts it).
            inside = module.startswith(name + ".")
            if known[name].name != "__init__.py" or (name in names and not inside):
                yield name


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """Module -> the package modules it imports."""
    known = _modules(root)
    return {m: set(_imported(m, p, known)) for m, p in known.items()}


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph)))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return found


def upward_imports(graph: Mapping[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) pairs where a module imports a higher layer's, or, in the core
    layer, a higher band's."""

    def up(m: str, d: str) -> bool:
        if layer_of(m) < 0:
            return False
        return layer_of(d) > layer_of(m) or band_of(d) > band_of(m) >= 0

    return sorted((m, d) for m, deps in graph.items() for d in deps if up(m, d))


def layer_counts(graph: Mapping[str, set[str]]) -> Counter[tuple[int, int]]:
    """How many module imports go from each layer to each (lower or same) layer."""
    counts: Counter[tuple[int, int]] = Counter()
    for m, deps in graph.items():
        for d in deps:
            if layer_of(m) >= 0 and layer_of(d) >= 0:
                counts[(layer_of(m), layer_of(d))] += 1
    return counts


def _figure(graph: Mapping[str, set[str]], path: Path) -> None:
    import matplotlib  # drawing is this command's job only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

    counts = layer_counts(graph)
    modules = Counter(layer_of(m) for m in graph if layer_of(m) >= 0)
    n = len(LAYERS)
    fig, ax = plt.subplots(figsize=(9, 1.15 * n + 0.6))
    ax.set_xlim(0, 10)
    ax.set_ylim(-0.6, n)
    ax.axis("off")
    for i, (name, prefixes) in enumerate(LAYERS):
        y = i
        ax.add_patch(FancyBboxPatch((0.2, y), 5.2, 0.62, boxstyle="round,pad=0.04", fc="#e8eef7", ec="#345"))
        ax.text(0.4, y + 0.38, name, fontsize=12, weight="bold", va="center")
        short = ", ".join(p.removeprefix("swarmrec.") for p in prefixes)
        ax.text(0.4, y + 0.12, short, fontsize=7.5, va="center", color="#333")
        ax.text(5.25, y + 0.38, f"{modules[i]} modules", fontsize=8, ha="right", va="center", color="#555")
    for (src, dst), k in sorted(counts.items()):
        if src == dst:
            continue
        x = 5.7 + 0.35 * (src - dst) + 0.12 * dst
        arrow = FancyArrowPatch(
            (x, src + 0.3),
            (x, dst + 0.55),
            arrowstyle="-|>",
            mutation_scale=9,
            lw=0.6 + 0.04 * k,
            color="#467",
        )
        ax.add_patch(arrow)
    own = sum(k for (s, d), k in counts.items() if s == d)
    down = sum(k for (s, d), k in counts.items() if s > d)
    ax.text(
        0.2,
        -0.45,
        f"imports read from the code: {down} to lower layers (arrows, width by count), {own} within a layer, "
        f"{len(upward_imports(graph))} upward, {len(cycles(graph))} cycles",
        fontsize=8,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m swarmrec.layers", description=__doc__.splitlines()[0])
    parser.add_argument("--figure", type=Path, help="draw the layers and the imports between them (PNG)")
    args = parser.parse_args(argv)
    graph = import_graph()
    for (src, dst), k in sorted(layer_counts(graph).items(), reverse=True):
        print(f"{LAYERS[src][0]:>12} -> {LAYERS[dst][0]:<12} {k:4d} imports")
    bad, loops = upward_imports(graph), cycles(graph)
    for m, d in bad:
        print(f"upward: {m} imports {d}")
    for c in loops:
        print("cycle: " + " <-> ".join(c))
    if args.figure is not None:
        _figure(graph, args.figure)
    return 1 if bad or loops else 0


if __name__ == "__main__":
    sys.exit(main())
