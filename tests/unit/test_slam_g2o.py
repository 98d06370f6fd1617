"""The g2o reader and writer: round trips, gtsam's reader as a cross-check, refusals with file:line."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from swarmrec.errors import DatasetError
from swarmrec.slam.errors import G2oError, G2oInformationError, G2oKeyError, G2oQuaternionError, GraphError
from swarmrec.slam.g2o import parse_g2o, read_g2o, read_robot_folder, write_g2o
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose, so3_exp
from tests.slam_graphs import make_graph

A0, A1, A5, B0 = pose_key(0, 0), pose_key(0, 1), pose_key(0, 5), pose_key(1, 0)
UNIT_INFO = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"
VERTEX_A0 = f"VERTEX_SE3:QUAT {A0} 0 0 0 0 0 0 1"
VERTEX_A1 = f"VERTEX_SE3:QUAT {A1} 1 0 0 0 0 0 1"
EDGE_A0_A1 = f"EDGE_SE3:QUAT {A0} {A1} 1 0 0 0 0 0 1 {UNIT_INFO}"


def write(tmp_path: Path, *lines: str, name: str = "graph.g2o") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def assert_same_graph(a: PoseGraph, b: PoseGraph) -> None:
    assert a.keys == b.keys
    for key in a.keys:
        assert a.poses[key].rotation == pytest.approx(b.poses[key].rotation, abs=1e-12)
        assert a.poses[key].translation == pytest.approx(b.poses[key].translation, abs=1e-12)
    assert len(a.edges) == len(b.edges)
    for x, y in zip(
        sorted(a.edges, key=lambda e: e.keys), sorted(b.edges, key=lambda e: e.keys), strict=True
    ):
        assert (x.source, x.target) == (y.source, y.target)
        assert x.measurement.rotation == pytest.approx(y.measurement.rotation, abs=1e-12)
        assert x.measurement.translation == pytest.approx(y.measurement.translation, abs=1e-12)
        assert x.information == pytest.approx(y.information, abs=1e-9)


def test_write_then_read_gives_back_the_same_graph(tmp_path: Path) -> None:
    graph, _ = make_graph(2, 4, sigma_r=0.05, sigma_t=0.1, initial_noise=0.2)
    # One edge with a full information matrix, cross blocks included.
    rng = np.random.default_rng(3)
    root = rng.normal(size=(6, 6))
    full = root @ root.T + 6 * np.eye(6)
    edges = (
        *graph.edges[:-1],
        Edge(graph.edges[-1].source, graph.edges[-1].target, graph.edges[-1].measurement, full),
    )
    graph = graph.with_edges(edges)
    assert_same_graph(read_g2o(write_g2o(tmp_path / "out.g2o", graph)), graph)


def test_reader_agrees_with_gtsam_read_g2o(tmp_path: Path) -> None:
    graph, _ = make_graph(2, 3, sigma_r=0.05, sigma_t=0.1, initial_noise=0.1)
    info = np.diag([4.0, 5.0, 6.0, 1.0, 2.0, 3.0])
    info[0, 4] = info[4, 0] = info[1, 3] = info[3, 1] = 0.5  # a symmetric cross block: both conventions agree
    graph = graph.with_edges(Edge(e.source, e.target, e.measurement, info) for e in graph.edges)
    path = write_g2o(tmp_path / "g.g2o", graph)
    ours = read_g2o(path)
    factors, values = gtsam.readG2o(str(path), True)
    assert sorted(values.keys()) == list(ours.keys)
    for key in ours.keys:
        assert values.atPose3(key).matrix() == pytest.approx(ours.poses[key].matrix(), abs=1e-9)
    for n, edge in enumerate(ours.edges):
        factor = factors.at(n)
        assert list(factor.keys()) == [edge.source, edge.target]
        assert factor.measured().matrix() == pytest.approx(edge.measurement.matrix(), abs=1e-9)
        assert factor.noiseModel().information() == pytest.approx(edge.information, abs=1e-9)


def test_information_blocks_are_permuted_to_rotation_first(tmp_path: Path) -> None:
    # g2o order (x y z qx qy qz): I11 = 1 (x), I14 = 0.5 (x with qx), I44 = 7 (qx), I66 = 9 (qz)
    upper = np.zeros((6, 6))
    upper[np.diag_indices(6)] = [1, 2, 3, 7, 8, 9]
    upper[0, 3] = 0.5
    info = " ".join(str(v) for v in upper[np.triu_indices(6)])
    path = write(tmp_path, VERTEX_A0, VERTEX_A1, f"EDGE_SE3:QUAT {A0} {A1} 1 0 0 0 0 0 1 {info}")
    omega = read_g2o(path).edges[0].information
    assert np.diag(omega) == pytest.approx([7, 8, 9, 1, 2, 3])
    assert omega[0, 3] == omega[3, 0] == 0.5  # (rotation x, translation x)


def test_a_slightly_unnormalised_quaternion_is_normalised(tmp_path: Path) -> None:
    path = write(tmp_path, f"VERTEX_SE3:QUAT {A0} 0 0 0 0 0 0.6 0.8004", VERTEX_A1, EDGE_A0_A1)
    rotation = read_g2o(path).poses[A0].rotation
    assert rotation @ rotation.T == pytest.approx(np.eye(3), abs=1e-12)


@pytest.mark.parametrize(
    ("line", "error", "message"),
    [
        (f"VERTEX_SE3:QUAT {A0} 0 0 0 0 0 0", G2oError, "needs a key and 7 numbers, got 7 fields"),
        (f"VERTEX_SE3:QUAT {A5} 0 zero 0 0 0 0 1", G2oError, "'zero' is not a number"),
        (f"VERTEX_SE3:QUAT {A5} 0 nan 0 0 0 0 1", G2oError, "not finite"),
        ("VERTEX_SE3:QUAT -4 0 0 0 0 0 0 1", G2oError, "outside"),
        (f"VERTEX_SE3:QUAT {A5} 0 0 0 0 0 0.6 0.7", G2oQuaternionError, "norm 0.921954, 0.078 from 1"),
        (f"VERTEX_SE2 {A0} 0 0 0", G2oError, "unsupported g2o tag 'VERTEX_SE2'"),
        (f"EDGE_SE3:QUAT {A0} {A1} 1 0 0 0 0 0 1 1 0 0", G2oError, "got 12 fields"),
        (f"EDGE_SE3:QUAT {A0} {A0} 1 0 0 0 0 0 1 {UNIT_INFO}", G2oKeyError, "to itself"),
        (
            f"EDGE_SE3:QUAT {A0} {B0} 1 0 0 0 0 0 1 {UNIT_INFO}",
            G2oKeyError,
            "uses b0, a vertex no file declares",
        ),
        (f"VERTEX_SE3:QUAT {A1} 1 0 0 0 0 0 1", G2oKeyError, "a1 already declared on line 2"),
    ],
)
def test_bad_lines_are_refused_with_file_and_line(
    tmp_path: Path, line: str, error: type, message: str
) -> None:
    path = write(tmp_path, VERTEX_A0, VERTEX_A1, "# a comment and a blank line", "", line)
    with pytest.raises(error) as caught:
        read_g2o(path)
    assert isinstance(caught.value, DatasetError)
    assert f"{path}:5: " in str(caught.value) and message in str(caught.value)


@pytest.mark.parametrize(
    ("info", "message"),
    [
        ("1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 0", "singular"),
        ("1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 -2", "not positive definite"),
        ("1 2 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1", "not positive definite"),
        ("1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 inf", "not finite"),
    ],
)
def test_unusable_information_matrices_are_refused(tmp_path: Path, info: str, message: str) -> None:
    path = write(tmp_path, VERTEX_A0, VERTEX_A1, f"EDGE_SE3:QUAT {A0} {A1} 1 0 0 0 0 0 1 {info}")
    with pytest.raises(G2oError, match=message) as caught:
        read_g2o(path)
    assert f"{path}:3" in str(caught.value)
    if message != "not finite":
        assert isinstance(caught.value, G2oInformationError)


def test_a_non_symmetric_information_matrix_is_refused_in_memory() -> None:
    info = np.eye(6)
    info[0, 5] = 0.3
    with pytest.raises(GraphError, match="not symmetric"):
        Edge(A0, A1, Pose.identity(), info)


def test_unsupported_lines_can_be_skipped_and_counted(tmp_path: Path) -> None:
    path = write(tmp_path, "FIX 0", VERTEX_A0, VERTEX_A1, EDGE_A0_A1, "VERTEX_XYZ 9 0 0 0")
    assert parse_g2o(path, skip_unsupported=True).skipped == 2
    assert len(read_g2o(path, skip_unsupported=True).edges) == 1


def write_folder(tmp_path: Path, graph: PoseGraph) -> Path:
    folder = tmp_path / "team"
    for robot in graph.robots:
        keys = graph.robot_keys(robot)
        write_g2o(folder / f"{robot}.g2o", graph, keys=keys, edges=graph.robot_edges(robot))
    return folder


def test_robot_folder_keeps_each_separator_once(tmp_path: Path) -> None:
    graph, _ = make_graph(3, 4, sigma_r=0.02, sigma_t=0.05)
    folder = write_folder(tmp_path, graph)
    team = read_robot_folder(folder)
    assert team.robot_files == (folder / "0.g2o", folder / "1.g2o", folder / "2.g2o")
    assert_same_graph(team.graph, graph)
    assert team.graph.separator_counts() == {(0, 1): 2, (1, 2): 2}
    assert team.full_graph is None


def test_full_graph_with_plain_keys_is_checked_against_the_robot_files(tmp_path: Path) -> None:
    graph, _ = make_graph(2, 3)
    # Plain keys of fullGraph.g2o are Symbol indices, so the robots' indices must not overlap:
    # robot 0 keeps a0..a2, robot 1's poses become b3..b5.
    index = {k: n for n, k in enumerate(graph.keys)}

    def symbol(key: int) -> int:
        return pose_key(graph.robot_of(key), index[key])

    team = PoseGraph(
        {symbol(k): p for k, p in graph.poses.items()},
        tuple(Edge(symbol(e.source), symbol(e.target), e.measurement, e.information) for e in graph.edges),
    )
    plain = PoseGraph(
        {index[k]: p for k, p in graph.poses.items()},
        tuple(Edge(index[e.source], index[e.target], e.measurement, e.information) for e in graph.edges),
    )
    folder = write_folder(tmp_path, team)
    write_g2o(folder / "fullGraph.g2o", plain)
    assert read_robot_folder(folder).full_graph == folder / "fullGraph.g2o"
    write_g2o(folder / "fullGraph.g2o", plain.with_edges(plain.edges[:-1]))
    with pytest.raises(G2oError, match=r"fullGraph\.g2o: 5 edges, the robot files hold 6"):
        read_robot_folder(folder)


def test_separators_that_differ_between_the_two_files_are_refused(tmp_path: Path) -> None:
    graph, _ = make_graph(2, 3)
    folder = write_folder(tmp_path, graph)
    separator = graph.separators()[0]
    changed = Edge(
        separator.source,
        separator.target,
        Pose(separator.measurement.rotation @ so3_exp([0.0, 0.0, 0.1]), separator.measurement.translation),
        separator.information,
    )
    edges = [changed if e is separator else e for e in graph.robot_edges(1)]
    write_g2o(folder / "1.g2o", graph, keys=graph.robot_keys(1), edges=edges)
    with pytest.raises(G2oError, match=r"1\.g2o:\d+: separator a0-b0 differs from the one in .*0\.g2o:\d+"):
        read_robot_folder(folder)


def test_robot_folder_refusals(tmp_path: Path) -> None:
    graph, _ = make_graph(2, 3)
    folder = write_folder(tmp_path, graph)
    (folder / "3.g2o").write_text("")
    with pytest.raises(G2oError, match=r"2\.g2o is missing"):
        read_robot_folder(folder)
    (folder / "3.g2o").unlink()
    # Robot 1's file declaring one of robot 0's keys.
    write_g2o(folder / "1.g2o", graph, keys=[*graph.robot_keys(1), A0], edges=graph.robot_edges(1))
    with pytest.raises(G2oKeyError, match=r"1\.g2o:1: vertex a0 is not a key of robot 1"):
        read_robot_folder(folder)
    with pytest.raises(G2oError, match="no robot files"):
        read_robot_folder(tmp_path)
