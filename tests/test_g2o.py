"""torchsgal.estimation.g2o against GTSAM's readers (gtsam/slam/dataset.cpp) on the shared data
and on files with full (off-diagonal) information matrices, and read/write round trips."""
from pathlib import Path

import numpy as np
import pytest
import torch

import torchsgal as ts
from torchsgal.estimation.g2o import EDGE_TAGS, PoseGraph, odometry_initial_guess, read_pose_graph, write_pose_graph

gtsam = pytest.importorskip("gtsam")

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SWAP = [3, 4, 5, 0, 1, 2]  # GTSAM's Pose3 tangent [omega, v] <-> torchsgal's [rho, phi]


@pytest.fixture(scope="module")
def data() -> Path:
    # a missing data folder fails (it is part of the checkout's environment), never skips
    assert (DATA / "sphere2500.txt").is_file(), f"shared data not found at {DATA}"
    return DATA


def gtsam_information(factor) -> np.ndarray:
    R = factor.noiseModel().R()
    return R.T @ R


def check_against_gtsam(graph: PoseGraph, factors, swap: bool):
    assert len(factors) == graph.edges.shape[0]
    keys = np.array([[f.keys()[0], f.keys()[1]] for f in factors])
    np.testing.assert_array_equal(graph.edge_ids.numpy(), keys)
    Z = np.stack([f.measured().matrix() for f in factors])
    np.testing.assert_allclose(graph.measurements.as_matrix().numpy(), Z, rtol=0, atol=1e-12)
    W = np.stack([gtsam_information(f) for f in factors])
    if swap:
        W = W[:, SWAP][:, :, SWAP]
    np.testing.assert_allclose(graph.information.numpy(), W, rtol=1e-12, atol=1e-12)


def random_graph(group, n=6, edges=((0, 1), (1, 2), (2, 0), (3, 4), (5, 3), (1, 5)), seed=0,
                 poses=True, edge_tag="EDGE_SE3:QUAT", ids=None):
    g = torch.Generator().manual_seed(seed)
    E = len(edges)
    d = group.dof
    A = torch.randn(E, d, d, generator=g, dtype=torch.float64)
    info = A @ A.transpose(-1, -2) + d * torch.eye(d, dtype=torch.float64)  # full SPD
    ids = torch.arange(n, dtype=torch.int64) * 3 + 2 if ids is None else ids
    return PoseGraph(group=group, ids=ids,
                     poses=group.random(n, dtype=torch.float64, generator=g) if poses else None,
                     edges=torch.tensor(edges, dtype=torch.int64),
                     measurements=group.random(E, dtype=torch.float64, generator=g),
                     information=info, edge_tag=edge_tag)


# --------------------------------------------------------------------------- shared data
def test_sphere2500_matches_gtsam(data):
    graph = read_pose_graph(data / "sphere2500.txt")
    assert graph.group is ts.SE3 and graph.edge_tag == "EDGE3" and graph.poses is None
    assert graph.ids.tolist() == list(range(2500))
    check_against_gtsam(graph, gtsam.parse3DFactors(str(data / "sphere2500.txt")), swap=True)


def test_pose3example_matches_gtsam(data):
    path = data / "pose3example-grid.txt"
    graph = read_pose_graph(path)
    g, values = gtsam.readG2o(str(path), True)
    factors = [g.at(k) for k in range(g.size())]
    check_against_gtsam(graph, factors, swap=True)
    assert graph.ids.tolist() == sorted(values.keys())
    P = np.stack([values.atPose3(k).matrix() for k in graph.ids.tolist()])
    np.testing.assert_allclose(graph.poses.as_matrix().numpy(), P, rtol=0, atol=1e-12)


def test_w100_matches_gtsam_toro(data):
    path = data / "w100.graph"
    graph = read_pose_graph(path)
    assert graph.group is ts.SE2 and graph.edge_tag == "EDGE2"
    g, values = gtsam.load2D(str(path), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    check_against_gtsam(graph, [g.at(k) for k in range(g.size())], swap=False)
    assert graph.ids.tolist() == sorted(values.keys())
    P = np.stack([values.atPose2(k).matrix() for k in graph.ids.tolist()])
    np.testing.assert_allclose(graph.poses.as_matrix().numpy(), P, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- full information
@pytest.mark.parametrize("edge_tag", ["EDGE_SE3:QUAT", "EDGE3"])
def test_full_information_3d_read_by_gtsam(tmp_path, edge_tag):
    graph = random_graph(ts.SE3, edge_tag=edge_tag, poses=False)
    path = tmp_path / "g.txt"
    write_pose_graph(path, graph)
    factors = gtsam.parse3DFactors(str(path))
    back = read_pose_graph(path)
    check_against_gtsam(back, factors, swap=True)
    torch.testing.assert_close(back.information, graph.information, rtol=1e-14, atol=0)


@pytest.mark.parametrize("edge_tag", ["EDGE_SE2", "EDGE2"])
def test_full_information_2d_read_by_gtsam(tmp_path, edge_tag):
    graph = random_graph(ts.SE2, edge_tag=edge_tag)
    path = tmp_path / "g.graph"
    write_pose_graph(path, graph)
    fmt = gtsam.NoiseFormat.NoiseFormatG2O if edge_tag == "EDGE_SE2" else gtsam.NoiseFormat.NoiseFormatTORO
    g, values = gtsam.load2D(str(path), noiseFormat=fmt, smart=False)
    back = read_pose_graph(path)
    check_against_gtsam(back, [g.at(k) for k in range(g.size())], swap=False)
    torch.testing.assert_close(back.information, graph.information, rtol=1e-14, atol=0)
    P = np.stack([values.atPose2(k).matrix() for k in back.ids.tolist()])
    np.testing.assert_allclose(back.poses.as_matrix().numpy(), P, rtol=0, atol=1e-12)


def test_gtsam_written_file_reads_the_same(data, tmp_path):
    g, values = gtsam.readG2o(str(data / "pose3example-grid.txt"), True)
    path = tmp_path / "gtsam.g2o"
    gtsam.writeG2o(g, values, str(path))
    ours, theirs = read_pose_graph(data / "pose3example-grid.txt"), read_pose_graph(path)
    assert torch.equal(ours.edges, theirs.edges) and torch.equal(ours.ids, theirs.ids)
    # GTSAM writes 6 significant digits
    torch.testing.assert_close(theirs.measurements.as_matrix(), ours.measurements.as_matrix(),
                               rtol=0, atol=1e-5)
    torch.testing.assert_close(theirs.information, ours.information, rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("edge_tag", EDGE_TAGS)
def test_round_trip(tmp_path, edge_tag):
    group = ts.SE3 if edge_tag in ("EDGE_SE3:QUAT", "EDGE3") else ts.SE2
    graph = random_graph(group, edge_tag=edge_tag, seed=4)
    path = tmp_path / "g.txt"
    write_pose_graph(path, graph)
    back = read_pose_graph(path)
    assert back.group is group and back.edge_tag == edge_tag
    assert torch.equal(back.ids, graph.ids) and torch.equal(back.edges, graph.edges)
    torch.testing.assert_close(back.measurements.as_matrix(), graph.measurements.as_matrix(),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(back.poses.as_matrix(), graph.poses.as_matrix(), rtol=0, atol=1e-12)
    torch.testing.assert_close(back.information, graph.information, rtol=1e-15, atol=0)


@pytest.mark.parametrize("name", ["sphere2500.txt", "pose3example-grid.txt", "w100.graph"])
def test_round_trip_shared_data_in_other_format(data, tmp_path, name):
    graph = read_pose_graph(data / name)
    other = {"EDGE3": "EDGE_SE3:QUAT", "EDGE_SE3:QUAT": "EDGE3", "EDGE2": "EDGE_SE2"}[graph.edge_tag]
    path = tmp_path / "g.txt"
    write_pose_graph(path, graph, edge_tag=other)
    back = read_pose_graph(path)
    assert back.edge_tag == other and torch.equal(back.edges, graph.edges)
    torch.testing.assert_close(back.measurements.as_matrix(), graph.measurements.as_matrix(),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(back.information, graph.information, rtol=1e-15, atol=0)


# --------------------------------------------------------------------------- initial guess
def test_odometry_initial_guess_matches_gtsam_load2d(data, tmp_path):
    # GTSAM's load2D chains the edges for a file without vertices
    edges_only = tmp_path / "w100_edges.graph"
    edges_only.write_text("".join(line for line in (data / "w100.graph").read_text().splitlines(True)
                                  if line.startswith("EDGE2")))
    graph = read_pose_graph(edges_only)
    _, values = gtsam.load2D(str(edges_only), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    P = np.stack([values.atPose2(k).matrix() for k in graph.ids.tolist()])
    np.testing.assert_allclose(odometry_initial_guess(graph).as_matrix().numpy(), P, rtol=0, atol=1e-9)


def test_odometry_initial_guess_sphere2500_matches_gtsam_compose(data):
    graph = read_pose_graph(data / "sphere2500.txt")
    poses = {}
    for f in gtsam.parse3DFactors(str(data / "sphere2500.txt")):
        i, j = f.keys()
        poses.setdefault(i, gtsam.Pose3())
        if j not in poses:
            poses[j] = poses[i].compose(f.measured())
    P = np.stack([poses[k].matrix() for k in range(2500)])
    np.testing.assert_allclose(odometry_initial_guess(graph).as_matrix().numpy(), P, rtol=0, atol=1e-9)


@pytest.mark.parametrize("group", [ts.SE2, ts.SE3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_odometry_initial_guess_keeps_the_graph_dtype(group, dtype):
    """A graph of float32 measurements gives float32 poses (the chain runs in float64 on the host)."""
    graph = random_graph(group, poses=False)
    graph.measurements = graph.measurements.to(dtype=dtype)
    graph.information = graph.information.to(dtype)
    guess = odometry_initial_guess(graph)
    assert isinstance(guess, group) and guess.dtype == dtype and guess.batch_shape == (6,)
    # the chain by hand: edges (0,1) (1,2) (2,0) (3,4) (5,3) (1,5) place 0 = I, 1 = Z01,
    # 2 = Z01 Z12, 3 = I, 4 = Z34, 5 = I (edge (5, 3) meets 5 first: an edge's first vertex
    # not yet placed is put at the identity)
    Z = graph.measurements.as_matrix().double().numpy()
    eye = np.eye(Z.shape[-1])
    P = np.stack([eye, Z[0], Z[0] @ Z[1], eye, Z[3], eye])
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(guess.as_matrix().double().numpy(), P, rtol=0, atol=tol)


# --------------------------------------------------------------------------- errors
@pytest.mark.parametrize("text, message", [
    ("VERTEX2 0 0 0 0\nEDGE2 0 1 1 0 zero 1 0 1 1 0 0\n", r":2: EDGE2 field 5, token 'zero', is not a finite number"),
    ("EDGE2 0 1 1 0 0 1 0 1 1 0\n", r":1: EDGE2 needs 11 fields after the tag \(2 ids, 9 numbers\), got 10"),
    ("EDGE2 0 -1 1 0 0 1 0 1 1 0 0\n", r":1: EDGE2 field 2, token '-1', is not a vertex id"),
    ("EDGE2 0 1 1 0 nan 1 0 1 1 0 0\n", r"token 'nan', is not a finite number"),
    ("\n# comment\nLANDMARK 0 1 1 1\n", r":3: unknown tag 'LANDMARK'"),
    ("VERTEX2 0 0 0 0\n", r"needs edges of exactly one format"),
    ("EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n", r"exactly one format"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n", r"do not match the edges"),
    ("VERTEX2 0 0 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n", r"vertex 1 of an edge has no vertex line"),
    ("VERTEX2 0 0 0 0\nVERTEX2 0 0 0 0\nEDGE2 0 0 1 0 0 1 0 1 1 0 0\n", r"more than one vertex line"),
    ("EDGE2 0 99999999999999999999 1 0 0 1 0 1 1 0 0\n",
     r":1: EDGE2 field 2, token '99999999999999999999', is not a vertex id \(an integer in \[0, 2\^63\)\)"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 0\n"
     "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n",
     r":2: VERTEX_SE3:QUAT fields 5-8, the quaternion \(qx qy qz qw\), are all zero"),
])
def test_malformed_files(tmp_path, text, message):
    path = tmp_path / "bad.graph"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_pose_graph(path)


def test_bytes_that_are_not_text(tmp_path):
    """A byte that is not UTF-8 in a data line is an error naming the file and line (not a
    UnicodeDecodeError at a position of the decoder's buffer, naming neither); in a comment it
    is skipped with the comment."""
    path = tmp_path / "bad.graph"
    path.write_bytes(b"# caf\xe9\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 \xff 1 0 1 1 0 0\n")
    with pytest.raises(ValueError, match=r"bad\.graph:3: EDGE2 field 5, token .*, is not a finite number"):
        read_pose_graph(path)
    path.write_bytes(b"# caf\xe9\nEDGE2 0 1 1 0 0 1 0 1 1 0 0\n")
    assert read_pose_graph(path).edges.tolist() == [[0, 1]]


def test_write_errors(tmp_path):
    graph = random_graph(ts.SE2, edge_tag="EDGE2")
    with pytest.raises(ValueError, match="edge_tag must be one of"):
        write_pose_graph(tmp_path / "g", graph, edge_tag="EDGE_SE3")
    with pytest.raises(ValueError, match="does not fit a graph of SE2"):
        write_pose_graph(tmp_path / "g", graph, edge_tag="EDGE3")
    bad = random_graph(ts.SE2, edge_tag="EDGE2")
    bad.information = bad.information[:, :2, :2]
    with pytest.raises(ValueError, match=r"information must have shape \(6, 3, 3\), got \(6, 2, 2\)"):
        write_pose_graph(tmp_path / "g", bad)
    bad = random_graph(ts.SE2, edge_tag="EDGE2")
    bad.edges = bad.edges + 10
    with pytest.raises(ValueError, match=r"edges must hold positions in ids, in \[0, 5\]"):
        write_pose_graph(tmp_path / "g", bad)
    bad = random_graph(ts.SE2, edge_tag="EDGE2")
    bad.poses = bad.poses[:3]
    with pytest.raises(ValueError, match=r"poses must be None or SE2 of batch \(6,\)"):
        write_pose_graph(tmp_path / "g", bad)


def test_write_refuses_an_asymmetric_information(tmp_path):
    """The formats hold the upper triangle: an asymmetric matrix would be read back as another
    one.  Rounding-level asymmetry is written (as its upper triangle)."""
    graph = random_graph(ts.SE2, edge_tag="EDGE_SE2")
    W = graph.information.clone()
    W[0, 0, 1] += 5.0
    graph.information = W
    with pytest.raises(ValueError, match=r"information must be symmetric .* got max \|W - W\^T\| = 5"):
        write_pose_graph(tmp_path / "g", graph)
    assert not (tmp_path / "g").exists()
    W = W.clone()
    W[0, 0, 1] = W[0, 1, 0] * (1 + 1e-15)
    graph.information = W
    write_pose_graph(tmp_path / "g", graph)
    torch.testing.assert_close(read_pose_graph(tmp_path / "g").information[0, 1, 0], W[0, 0, 1])


def test_odometry_initial_guess_checks_a_graph_made_by_hand():
    """Edges outside [0, N) (a negative one would wrap around to the last vertex) are refused."""
    graph = random_graph(ts.SE2, edge_tag="EDGE2")
    for edges in (graph.edges.clone().index_fill_(1, torch.tensor([1]), -1), graph.edges + 10):
        graph.edges = edges
        with pytest.raises(ValueError, match=r"edges must hold positions in ids, in \[0, 5\]"):
            odometry_initial_guess(graph)


@pytest.mark.parametrize("spoil, message", [
    (lambda g: setattr(g, "ids", g.ids - 3), r"ids must be >= 0 \(g2o and TORO vertex ids\), got -1"),
    (lambda g: setattr(g, "ids", torch.zeros_like(g.ids)), "ids must be distinct"),
    (lambda g: g.information.__setitem__((0, 0, 0), float("nan")), "information must be finite"),
    (lambda g: setattr(g, "measurements", ts.SE2(g.measurements.as_matrix().clone().index_fill_(
        -1, torch.tensor([2]), float("inf")))), "measurements must be finite"),
])
def test_write_refuses_what_the_reader_refuses(tmp_path, spoil, message):
    """A graph the reader would refuse (negative or repeated ids, non-finite numbers) is not
    written: the file could not be read back."""
    graph = random_graph(ts.SE2, edge_tag="EDGE2")
    graph.information = graph.information.clone()
    spoil(graph)
    with pytest.raises(ValueError, match=message):
        write_pose_graph(tmp_path / "g", graph)
    assert not (tmp_path / "g").exists()
