"""g2o pose graphs: ``VERTEX_SE3:QUAT`` and ``EDGE_SE3:QUAT`` lines, one file or one file per robot.

Line formats (whitespace separated)::

    VERTEX_SE3:QUAT key x y z qx qy qz qw
    EDGE_SE3:QUAT   key_i key_j x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66

An edge measures ``x_i^-1 x_j``; its 21 numbers are the upper triangle, row by
row, of the information matrix in g2o's order (translation, then rotation).
:class:`~swarmrec.slam.graph.Edge` keeps gtsam's order (rotation first), so the
reader permutes the blocks, ``Omega = P M P^T``, and the writer undoes it. (gtsam's
own ``readG2o`` copies the off-diagonal block without transposing it; the two
agree whenever that block is symmetric, as in every file we know, where it is zero.)
Like gtsam, the rotation part of the information is taken as given, in the
units of the tangent rotation vector.

Quaternions are normalised when their norm is within ``QUATERNION_TOLERANCE``
of 1 (text rounding) and refused beyond. Every refusal is a
:class:`~swarmrec.slam.errors.G2oError` naming the file and line.

A *robot folder* (:func:`read_robot_folder`) holds ``0.g2o``, ``1.g2o``, ...:
robot ``r``'s vertices (keys ``Symbol('a' + r, i)``, objects ``'A' + r``), its
edges and its separators, which are written in both robots' files and kept
once; optionally ``fullGraph.g2o``, the union, with plain integer keys (the
Symbol index) or Symbol keys, which is checked against the robot files.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmrec.slam.errors import G2oError, G2oInformationError, G2oKeyError, G2oQuaternionError
from swarmrec.slam.graph import Edge, PoseGraph, information_problem
from swarmrec.slam.keys import MAX_INDEX, describe_key, robot_of_key, symbol_chr, symbol_index
from swarmrec.slam.lie import FloatArray, Pose

__all__ = [
    "EDGE_TAG",
    "FULL_GRAPH_NAME",
    "QUATERNION_TOLERANCE",
    "VERTEX_TAG",
    "G2oFile",
    "RobotFile",
    "RobotFolder",
    "parse_g2o",
    "read_g2o",
    "read_robot_file",
    "read_robot_folder",
    "robot_file_name",
    "write_g2o",
]

VERTEX_TAG = "VERTEX_SE3:QUAT"
EDGE_TAG = "EDGE_SE3:QUAT"
FULL_GRAPH_NAME = "fullGraph.g2o"
# Files write about 6 significant digits, so a unit quaternion reads back
# within ~1e-6 of norm 1; a thousandth is far beyond rounding but still a rotation
# someone meant. Anything further is a bug upstream, not a rounding artefact.
QUATERNION_TOLERANCE = 1e-3
# Separators written in two robots' files must agree to this (relative) precision.
_SEPARATOR_TOLERANCE = 1e-6

_VERTEX_FIELDS = 9
_EDGE_FIELDS = 31
# g2o (translation, rotation) <-> gtsam (rotation, translation)
_BLOCK_SWAP = np.array([3, 4, 5, 0, 1, 2])
_UPPER = np.triu_indices(6)
_ROBOT_FILE = re.compile(r"^(\d+)\.g2o$")


@dataclass(frozen=True)
class G2oFile:
    """What one file declares, before keys are checked against other files.

    ``vertex_lines`` and ``edge_lines`` are 1-based line numbers, aligned with
    ``poses``' keys and ``edges``, so later checks can still point at a line.
    """

    path: Path
    poses: dict[int, Pose]
    vertex_lines: dict[int, int]
    edges: tuple[Edge, ...]
    edge_lines: tuple[int, ...]
    skipped: int = 0


@dataclass(frozen=True)
class RobotFolder:
    """A folder of per-robot g2o files, merged into one graph.

    ``graph`` holds every robot's vertices and edges, separators once;
    ``robot_files[r]`` is robot ``r``'s file; ``full_graph`` is the path of
    ``fullGraph.g2o`` when present (then checked to hold the same vertices and edges).
    """

    folder: Path
    graph: PoseGraph
    robot_files: tuple[Path, ...]
    full_graph: Path | None


def _key(token: str, path: Path, line: int) -> int:
    try:
        key = int(token)
    except ValueError:
        raise G2oError(path, f"vertex key {token!r} is not a non-negative integer", line) from None
    if not 0 <= key < 1 << 64:
        raise G2oError(path, f"vertex key {token} is outside 0..2^64-1", line)
    return key


def _numbers(tokens: list[str], path: Path, line: int) -> FloatArray:
    try:
        values = np.array([float(t) for t in tokens])
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise G2oError(path, f"{bad!r} is not a number", line) from None
    if not np.all(np.isfinite(values)):
        raise G2oError(path, "a value is not finite (nan or inf)", line)
    return values


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _pose(values: FloatArray, path: Path, line: int) -> Pose:
    quaternion = values[3:7]
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise G2oQuaternionError(
            path,
            f"quaternion (qx qy qz qw) has norm {norm:.6g}, {abs(norm - 1.0):.3g} from 1 "
            f"(more than the {QUATERNION_TOLERANCE:g} allowed for rounding)",
            line,
            norm=norm,
        )
    return Pose.from_quaternion(values[:3], quaternion / norm)


def _information(values: FloatArray, path: Path, line: int) -> FloatArray:
    g2o_order = np.zeros((6, 6))
    g2o_order[_UPPER] = values
    g2o_order = g2o_order + np.triu(g2o_order, 1).T
    information: FloatArray = g2o_order[np.ix_(_BLOCK_SWAP, _BLOCK_SWAP)]
    problem = information_problem(information)
    if problem is not None:
        raise G2oInformationError(path, problem, line)
    return information


def parse_g2o(path: str | Path, *, skip_unsupported: bool = False) -> G2oFile:
    """Read one g2o file's vertices and edges, checking each line on its own.

    Blank lines and ``#`` comments are ignored. Any tag other than
    ``VERTEX_SE3:QUAT`` and ``EDGE_SE3:QUAT`` is an error, or counted in
    ``skipped`` with ``skip_unsupported``. Keys of edges are not checked
    against vertices here (a robot's file refers to its neighbours' vertices):
    :func:`read_g2o` and :func:`read_robot_folder` do that.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise G2oError(path, f"cannot read: {exc}") from None
    poses: dict[int, Pose] = {}
    vertex_lines: dict[int, int] = {}
    edges: list[Edge] = []
    edge_lines: list[int] = []
    skipped = 0
    for number, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag == VERTEX_TAG:
            if len(tokens) != _VERTEX_FIELDS:
                raise G2oError(
                    path, f"{VERTEX_TAG} needs a key and 7 numbers, got {len(tokens) - 1} fields", number
                )
            key = _key(tokens[1], path, number)
            if key in poses:
                raise G2oKeyError(
                    path,
                    f"vertex {describe_key(key)} already declared on line {vertex_lines[key]}",
                    number,
                    key=key,
                )
            poses[key] = _pose(_numbers(tokens[2:], path, number), path, number)
            vertex_lines[key] = number
        elif tag == EDGE_TAG:
            if len(tokens) != _EDGE_FIELDS:
                raise G2oError(
                    path,
                    f"{EDGE_TAG} needs 2 keys, 7 numbers and 21 information entries, "
                    f"got {len(tokens) - 1} fields",
                    number,
                )
            source, target = _key(tokens[1], path, number), _key(tokens[2], path, number)
            if source == target:
                raise G2oKeyError(path, f"edge from {describe_key(source)} to itself", number, key=source)
            values = _numbers(tokens[3:], path, number)
            measurement = _pose(values[:7], path, number)
            edges.append(Edge(source, target, measurement, _information(values[7:], path, number)))
            edge_lines.append(number)
        elif skip_unsupported:
            skipped += 1
        else:
            raise G2oError(
                path,
                f"unsupported g2o tag {tag!r} (this reader takes {VERTEX_TAG} and {EDGE_TAG} only)",
                number,
            )
    return G2oFile(path, poses, vertex_lines, tuple(edges), tuple(edge_lines), skipped)


def _check_edge_keys(parsed: G2oFile, declared: Mapping[int, Pose]) -> None:
    for edge, line in zip(parsed.edges, parsed.edge_lines, strict=True):
        for key in edge.keys:
            if key not in declared:
                raise G2oKeyError(
                    parsed.path,
                    f"edge {describe_key(edge.source)}-{describe_key(edge.target)} "
                    f"uses {describe_key(key)}, a vertex no file declares",
                    line,
                    key=key,
                )


def read_g2o(path: str | Path, *, skip_unsupported: bool = False) -> PoseGraph:
    """A self-contained g2o file as a :class:`PoseGraph` (every edge's vertices declared in it)."""
    parsed = parse_g2o(path, skip_unsupported=skip_unsupported)
    _check_edge_keys(parsed, parsed.poses)
    return PoseGraph(parsed.poses, parsed.edges)


def _format(values: Iterable[float]) -> str:
    # 17 significant digits: every float64 reads back bit for bit.
    return " ".join(format(float(v), ".17g") for v in values)


def _pose_fields(pose: Pose) -> str:
    return _format([*pose.translation, *pose.quaternion()])


def write_g2o(
    path: str | Path,
    graph: PoseGraph,
    poses: Mapping[int, Pose] | None = None,
    *,
    keys: Iterable[int] | None = None,
    edges: Iterable[Edge] | None = None,
) -> Path:
    """Write a graph (vertices at ``poses``, default the graph's own) as g2o; returns the path.

    ``keys`` and ``edges`` restrict what is written (a robot's own file holds
    its vertices and every edge touching them). Vertices are sorted by key.
    """
    path = Path(path)
    at = graph.poses if poses is None else poses
    lines = [
        f"{VERTEX_TAG} {key} {_pose_fields(at[key])}" for key in sorted(graph.keys if keys is None else keys)
    ]
    for edge in graph.edges if edges is None else edges:
        g2o_order = edge.information[np.ix_(_BLOCK_SWAP, _BLOCK_SWAP)]
        lines.append(
            f"{EDGE_TAG} {edge.source} {edge.target} {_pose_fields(edge.measurement)} "
            f"{_format(g2o_order[_UPPER])}"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def robot_file_name(robot: int) -> str:
    return f"{robot}.g2o"


def _robot_files(folder: Path) -> tuple[Path, ...]:
    numbers = sorted(int(m.group(1)) for p in folder.iterdir() if (m := _ROBOT_FILE.match(p.name)))
    if not numbers:
        raise G2oError(folder, "no robot files (0.g2o, 1.g2o, ...) in this folder")
    expected = list(range(len(numbers)))
    if numbers != expected:
        gap = next(i for i, n in zip(expected, numbers, strict=True) if i != n)
        raise G2oError(folder, f"robot files must be numbered 0..n-1 without gaps: {gap}.g2o is missing")
    return tuple(folder / robot_file_name(n) for n in numbers)


def _same_edge(a: Edge, b: Edge) -> bool:
    def close(x: FloatArray, y: FloatArray) -> bool:
        return bool(np.allclose(x, y, rtol=_SEPARATOR_TOLERANCE, atol=_SEPARATOR_TOLERANCE))

    return (
        close(a.measurement.rotation, b.measurement.rotation)
        and close(a.measurement.translation, b.measurement.translation)
        and close(a.information, b.information)
    )


def _check_own_vertices(one: G2oFile, robot: int) -> None:
    for key in one.poses:
        if robot_of_key(key) != robot:
            raise G2oKeyError(
                one.path,
                f"vertex {describe_key(key)} is not a key of robot {robot} "
                f"(robot {robot}'s keys are Symbols '{chr(ord('a') + robot)}' or "
                f"'{chr(ord('A') + robot)}')",
                one.vertex_lines[key],
                key=key,
            )


@dataclass(frozen=True)
class RobotFile:
    """One robot's own g2o file: its vertices, its own edges and its separators.

    What a robot of a live team holds (the neighbours' vertices are not in it:
    a separator names a key the neighbour estimates).
    """

    path: Path
    robot: int
    poses: dict[int, Pose]
    edges: tuple[Edge, ...]
    separators: tuple[Edge, ...]


def read_robot_file(path: str | Path, robot: int) -> RobotFile:
    """Robot ``robot``'s file (``<r>.g2o`` of a robot folder) on its own.

    Every vertex must be one of the robot's keys; an edge between two of them
    must join declared vertices; every other edge must be a separator, from one
    of the robot's declared keys to a key of another robot.
    """
    one = parse_g2o(path)
    if not one.poses:
        raise G2oError(one.path, f"declares no vertex of robot {robot}")
    _check_own_vertices(one, robot)
    edges: list[Edge] = []
    separators: list[Edge] = []
    for edge, line in zip(one.edges, one.edge_lines, strict=True):
        owners = (robot_of_key(edge.source), robot_of_key(edge.target))
        if owners == (robot, robot):
            _check_edge_keys(G2oFile(one.path, {}, {}, (edge,), (line,)), one.poses)
            edges.append(edge)
            continue
        mine = [k for k, o in zip(edge.keys, owners, strict=True) if o == robot]
        other = [o for o in owners if o != robot]
        if len(mine) != 1 or other[0] is None:
            raise G2oKeyError(
                one.path,
                f"edge {describe_key(edge.source)}-{describe_key(edge.target)} is neither robot "
                f"{robot}'s own nor a separator from one of its keys to another robot's",
                line,
                key=edge.source,
            )
        if mine[0] not in one.poses:
            raise G2oKeyError(
                one.path,
                f"separator {describe_key(edge.source)}-{describe_key(edge.target)} uses "
                f"{describe_key(mine[0])}, which this file does not declare",
                line,
                key=mine[0],
            )
        separators.append(edge)
    return RobotFile(one.path, robot, one.poses, tuple(edges), tuple(separators))


def read_robot_folder(folder: str | Path) -> RobotFolder:
    """Read ``0.g2o``, ``1.g2o``, ... (and check ``fullGraph.g2o`` when present) into one graph."""
    folder = Path(folder)
    if not folder.is_dir():
        raise G2oError(folder, "not a folder")
    paths = _robot_files(folder)
    parsed = [parse_g2o(p) for p in paths]
    declared: dict[int, Pose] = {}
    where: dict[int, tuple[Path, int]] = {}
    for robot, one in enumerate(parsed):
        _check_own_vertices(one, robot)
        for key, pose in one.poses.items():
            if key in declared:
                first, line = where[key]
                raise G2oKeyError(
                    one.path,
                    f"vertex {describe_key(key)} already declared in {first}:{line}",
                    one.vertex_lines[key],
                    key=key,
                )
            declared[key] = pose
            where[key] = (one.path, one.vertex_lines[key])
    edges: list[Edge] = []
    separators: dict[tuple[int, int], tuple[Edge, Path, int]] = {}
    for robot, one in enumerate(parsed):
        _check_edge_keys(one, declared)
        for edge, line in zip(one.edges, one.edge_lines, strict=True):
            owners = (robot_of_key(edge.source), robot_of_key(edge.target))
            if robot not in owners:
                raise G2oKeyError(
                    one.path,
                    f"edge {describe_key(edge.source)}-{describe_key(edge.target)} "
                    f"touches none of robot {robot}'s vertices",
                    line,
                    key=edge.source,
                )
            if owners[0] == owners[1]:
                edges.append(edge)
                continue
            seen = separators.get(edge.keys)
            if seen is None:
                separators[edge.keys] = (edge, one.path, line)
                edges.append(edge)
            elif seen[1] != one.path:
                if not _same_edge(seen[0], edge):
                    raise G2oError(
                        one.path,
                        f"separator {describe_key(edge.source)}-{describe_key(edge.target)} "
                        f"differs from the one in {seen[1]}:{seen[2]}",
                        line,
                    )
            else:
                edges.append(edge)  # a second measurement in the same file is a measurement of its own
    graph = PoseGraph(declared, tuple(edges))
    full = folder / FULL_GRAPH_NAME
    if full.exists():
        _check_full_graph(full, graph)
    return RobotFolder(folder, graph, paths, full if full.exists() else None)


def _check_full_graph(path: Path, graph: PoseGraph) -> None:
    """``fullGraph.g2o`` must hold the robot files' vertices and edges (plain keys = Symbol index)."""
    parsed = parse_g2o(path)
    by_index: dict[int, int] = {}
    for key in graph.keys:
        if symbol_index(key) in by_index:
            by_index[symbol_index(key)] = -1  # ambiguous: two robots use this index
        else:
            by_index[symbol_index(key)] = key

    def mapped(key: int, line: int) -> int:
        if symbol_chr(key) != "\x00" or key > MAX_INDEX:
            return key
        full_key = by_index.get(key)
        if full_key is None or full_key < 0:
            why = "no robot file declares that index" if full_key is None else "several robots use that index"
            raise G2oKeyError(
                path, f"plain key {key} cannot be matched to a robot's Symbol: {why}", line, key=key
            )
        return full_key

    keys = {mapped(k, parsed.vertex_lines[k]) for k in parsed.poses}
    if keys != set(graph.poses):
        extra, missing = sorted(keys - set(graph.poses)), sorted(set(graph.poses) - keys)
        raise G2oError(
            path,
            f"vertices differ from the robot files ({len(extra)} extra, "
            f"{len(missing)} missing, e.g. "
            f"{describe_key((extra or missing)[0])})",
        )
    robot_edges: dict[tuple[int, int], list[Edge]] = {}
    for edge in graph.edges:
        robot_edges.setdefault(edge.keys, []).append(edge)
    for edge, line in zip(parsed.edges, parsed.edge_lines, strict=True):
        pair = (mapped(edge.source, line), mapped(edge.target, line))
        candidates = robot_edges.get(pair, [])
        if not any(_same_edge(edge, c) for c in candidates):
            raise G2oError(
                path,
                f"edge {describe_key(pair[0])}-{describe_key(pair[1])} is in no robot file "
                f"(or differs from it)",
                line,
            )
    if len(parsed.edges) != len(graph.edges):
        raise G2oError(path, f"{len(parsed.edges)} edges, the robot files hold {len(graph.edges)}")
