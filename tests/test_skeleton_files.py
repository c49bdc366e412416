"""Skeleton files: SWC and CSV node tables read as written, repaired by an explicit policy with
every repair counted, every problem in one error, SWC round trips, and a file rendered through
the CLI. Every expected value is written in the test (or computed here in float64 NumPy)."""

from __future__ import annotations

import json

import numpy as np
from pathlib import Path
import pytest

from jskel import cli, executor
from jskel.skeletons import (
    MISSING,
    RepairPolicy,
    TYPE_COLORS,
    from_arrays,
    label_colors,
    load,
    read_node_table,
    read_swc,
    repair,
    write_swc,
)


def _write(tmp_path, name: str, text: str):
    p = tmp_path / name
    p.write_text(text)
    return p


QUIRKS = """# a NeuroMorpho.Org-style header
#  id type x y z radius parent

7 1 0.0 0.0 0.0 4.5 -1
12 3 1.5 10 0 1.25 7   # inline comment
3 3 1.5 20 -2 0.5 12
40 3 2 30 -2 0.75 3
9 2 0 -8 0 0.8 7
# a second tree (several roots), with a parent that comes after its child
101 4 50 0 0 1 100
100 4 50 -5 0 2 -1
"""


def test_swc_keeps_order_ids_types_and_roots(tmp_path):
    sk = read_swc(_write(tmp_path, "q.swc", QUIRKS))
    np.testing.assert_array_equal(sk.ids, [7, 12, 3, 40, 9, 101, 100])
    np.testing.assert_array_equal(sk.labels, [1, 3, 3, 3, 2, 4, 4])
    np.testing.assert_array_equal(sk.parents, [-1, 0, 1, 2, 0, 6, -1])
    np.testing.assert_array_equal(sk.parent_ids, [-1, 7, 12, 3, 7, 100, -1])
    np.testing.assert_array_equal(sk.joints, [[0, 0, 0], [1.5, 10, 0], [1.5, 20, -2], [2, 30, -2], [0, -8, 0], [50, 0, 0], [50, -5, 0]])
    # a child thicker than its parent (12 -> 3 -> 40: 1.25, 0.5, 0.75) stays as written
    np.testing.assert_array_equal(sk.radii, [4.5, 1.25, 0.5, 0.75, 0.8, 1.0, 2.0])
    fixed, report = repair(sk)
    np.testing.assert_array_equal(fixed.radii, sk.radii)
    assert all(v["count"] == 0 for v in report.values()), report


def test_unknown_radii_take_the_parents_the_median_or_a_number(tmp_path):
    body = "1 1 0 0 0 0 -1\n2 3 0 1 0 2 1\n3 3 0 2 0 0 2\n4 3 0 3 0 -1 3\n5 3 0 4 0 nan 4\n6 3 0 5 0 3 5\n7 3 1 1 0 4 2\n"
    sk = read_swc(_write(tmp_path, "r.swc", body))
    # root 1 has no known ancestor: the median of the known radii (2, 3, 4) = 3
    fixed, rep = repair(sk, RepairPolicy(unknown_radius="parent"))
    np.testing.assert_array_equal(fixed.radii, [3, 2, 2, 2, 2, 3, 4])
    assert rep["unknown_radius"] == {"count": 4, "ids": [1, 3, 4, 5]}
    fixed, _ = repair(sk, RepairPolicy(unknown_radius="median"))
    np.testing.assert_array_equal(fixed.radii, [3, 2, 3, 3, 3, 3, 4])
    fixed, _ = repair(sk, RepairPolicy(unknown_radius=0.25, min_radius=2.5))
    np.testing.assert_array_equal(fixed.radii, [2.5, 2.5, 2.5, 2.5, 2.5, 3, 4])
    fixed, rep = repair(sk, RepairPolicy(min_radius=2.5))
    assert rep["min_radius"] == {"count": 4, "ids": [2, 3, 4, 5]}
    np.testing.assert_array_equal(fixed.radii, [3, 2.5, 2.5, 2.5, 2.5, 3, 4])


def test_coincident_nodes_merge_into_their_parent(tmp_path):
    # 3 sits on 2, and 4 on 3 (a chain of duplicates): both merge into 2; 5 and 6 re-parented to 2
    body = "1 3 0 0 0 1 -1\n2 3 0 1 0 1 1\n3 3 0 1 0 2 2\n4 3 0 1 0 3 3\n5 3 0 2 0 1 4\n6 3 1 2 0 1 3\n"
    sk = read_swc(_write(tmp_path, "d.swc", body))
    fixed, rep = repair(sk)
    np.testing.assert_array_equal(fixed.ids, [1, 2, 5, 6])
    np.testing.assert_array_equal(fixed.parent_ids, [-1, 1, 2, 2])
    np.testing.assert_array_equal(fixed.parents, [-1, 0, 1, 1])
    np.testing.assert_array_equal(fixed.radii, [1, 1, 1, 1])
    assert rep["zero_length_merged"] == {"count": 2, "ids": [3, 4]}
    kept, rep = repair(sk, RepairPolicy(merge_zero_length=False))
    np.testing.assert_array_equal(kept.ids, [1, 2, 3, 4, 5, 6]) and rep["zero_length_merged"]["count"] == 0
    # a tolerance in file units merges nodes that nearly coincide
    near = read_swc(_write(tmp_path, "n.swc", "1 3 0 0 0 1 -1\n2 3 0 1 0 1 1\n3 3 0 1.01 0 1 2\n4 3 0 2 0 1 3\n"))
    fixed, rep = repair(near, RepairPolicy(merge_tolerance=0.02))
    np.testing.assert_array_equal(fixed.ids, [1, 2, 4]) and rep["zero_length_merged"]["ids"] == [3]


def test_soma_contour_kept_or_merged(tmp_path):
    # a soma contour: 8 type-1 nodes on a circle of radius 5 around (10, 20, 0), chained;
    # a dendrite leaves from contour node 14 and an axon from the root 11
    ang = np.arange(8) * np.pi / 4
    pts = np.stack([10 + 5 * np.cos(ang), 20 + 5 * np.sin(ang), np.zeros(8)], 1)
    lines = [f"{11 + k} 1 {x!r} {y!r} {z!r} 0.5 {-1 if k == 0 else 10 + k}" for k, (x, y, z) in enumerate(pts.tolist())]
    lines += ["30 3 10 40 0 1 14", "31 2 10 0 0 1 11"]
    sk = read_swc(_write(tmp_path, "soma.swc", "\n".join(lines) + "\n"))
    assert sk.ids.size == 10 and np.sum(sk.labels == 1) == 8
    kept, rep = repair(sk)
    assert kept.ids.size == 10 and rep["soma_merged"]["count"] == 0
    merged, rep = repair(sk, RepairPolicy(soma="merge"))
    np.testing.assert_array_equal(merged.ids, [11, 30, 31])
    np.testing.assert_array_equal(merged.parent_ids, [-1, 11, 11])
    np.testing.assert_allclose(merged.joints[0], [10, 20, 0], atol=1e-12)
    np.testing.assert_allclose(merged.radii[0], 5.0, rtol=1e-12)  # mean distance 5 > node radii 0.5
    assert rep["soma_merged"] == {"count": 7, "ids": [12, 13, 14, 15, 16]}
    # NeuroMorpho.Org's three-point soma (centre, +-r along y): one node of radius r at the centre
    three = "1 1 1 2 3 6 -1\n2 1 1 -4 3 6 1\n3 1 1 8 3 6 1\n4 3 1 20 3 1 1\n"
    merged, _ = repair(read_swc(_write(tmp_path, "three.swc", three)), RepairPolicy(soma="merge"))
    np.testing.assert_array_equal(merged.ids, [1, 4])
    np.testing.assert_allclose(merged.joints[0], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(merged.radii[0], 6.0)


def test_fragments_below_a_size_are_dropped(tmp_path):
    body = "1 3 0 0 0 1 -1\n2 3 0 1 0 1 1\n3 3 0 2 0 1 2\n10 3 5 0 0 1 -1\n11 3 5 1 0 1 10\n20 3 9 9 9 1 -1\n"
    sk = read_swc(_write(tmp_path, "f.swc", body))
    fixed, rep = repair(sk, RepairPolicy(drop_fragments_below=3))
    np.testing.assert_array_equal(fixed.ids, [1, 2, 3])
    assert rep["fragments_dropped"] == {"count": 3, "ids": [10, 11, 20]}
    assert repair(sk)[0].ids.size == 6


@pytest.mark.parametrize("header, sep", [
    ("node_id,label,x,y,z,radius,parent_id,type", ","),  # navis: type holds node kinds, not SWC types
    ("Treenode_ID , Parent_Treenode_ID , X , Y , Z , R", ","),  # CATMAID, with spaces and capitals
    ("ID,X,Y,Z,RADIUS,PARENT", ","),
])
def test_csv_node_tables_with_header_variants(tmp_path, header, sep):
    names = [h.strip().lower() for h in header.split(sep)]
    nodes = [(5, 0.0, 0.0, 0.0, 2.0, None), (8, 0.0, 3.5, 1.0, 1.5, 5), (6, 1.0, 7.0, 1.0, None, 8), (9, 4.0, 0.0, 0.0, 1.0, 5)]
    rows = []
    for i, x, y, z, r, par in nodes:
        cell = {"node_id": i, "treenode_id": i, "id": i, "x": x, "y": y, "z": z, "radius": r, "r": r, "label": 0,
                "type": "root" if par is None else "slab", "parent_id": par, "parent_treenode_id": par, "parent": par}
        if par is None:  # navis writes -1, CATMAID leaves the cell empty
            cell["parent_id"], cell["parent_treenode_id"], cell["parent"] = -1, "", "None"
        rows.append(sep.join("" if cell[n] is None else str(cell[n]) for n in names))
    sk = read_node_table(_write(tmp_path, "n.csv", header + "\n" + "\n".join(rows) + "\n"))
    np.testing.assert_array_equal(sk.ids, [5, 8, 6, 9])
    np.testing.assert_array_equal(sk.parents, [-1, 0, 1, 0])
    np.testing.assert_array_equal(sk.joints, [[0, 0, 0], [0, 3.5, 1], [1, 7, 1], [4, 0, 0]])
    np.testing.assert_array_equal(sk.radii[[0, 1, 3]], [2.0, 1.5, 1.0])
    assert np.isnan(sk.radii[2]) and np.all(sk.labels == 0)
    fixed, rep = load(tmp_path / "n.csv")  # auto: a .csv is a node table; the unknown radius is the parent's
    assert fixed.radii[2] == 1.5 and rep["unknown_radius"] == {"count": 1, "ids": [6]}


def test_csv_without_a_radius_column_names_what_is_missing(tmp_path):
    with pytest.raises(ValueError, match=r"skeleton\.file: the header has no column radius/r \(got id, x, y, z, parent\)"):
        read_node_table(_write(tmp_path, "n.csv", "id,x,y,z,parent\n1,0,0,0,-1\n"))


def test_433_bad_radii_are_one_error_with_the_count_and_the_first_ids(tmp_path):
    rng = np.random.default_rng(4)
    n = 1000
    ids = np.arange(n) * 3 + 10  # non-sequential ids
    bad = np.sort(rng.choice(n, 433, replace=False))
    r = np.full(n, 1.0)
    r[bad] = rng.choice([0.0, -1.0, np.nan], 433)
    lines = [f"{ids[k]} 3 {k} 0 0 {float(r[k])!r} {ids[k - 1] if k else -1}" for k in range(n)]
    sk = read_swc(_write(tmp_path, "bad.swc", "\n".join(lines) + "\n"))
    with pytest.raises(ValueError) as e:
        repair(sk, RepairPolicy(unknown_radius="error"))
    msg = str(e.value)
    assert len(msg.splitlines()) == 1, msg
    first = ", ".join(f"{ids[k]}: {r[k]:.6g}" for k in bad[:5])
    assert msg == f"skeleton.file radius: 433 nodes with radius <= 0 or not a number (ids {first}, ...)", msg


def test_every_problem_is_in_one_error(tmp_path):
    body = "\n".join([
        "1 3 0 0 0 1 -1",
        "2 3 0 1 0 0 1",  # radius 0
        "2 3 0 2 0 1 1",  # id 2 again
        "4 3 0 3 0 1 99",  # no node 99
        "5 3 0 4 0 1 6",  # 5 -> 6 -> 5: a cycle
        "6 3 0 5 0 1 5",
        "7 3 nan 6 0 1 1",  # non-finite coordinate
    ]) + "\n"
    sk = read_swc(_write(tmp_path, "all.swc", body))
    assert sk.parents[3] == MISSING
    with pytest.raises(ValueError) as e:
        repair(sk, RepairPolicy(unknown_radius="error"), field="object.skeleton.file")
    lines = str(e.value).splitlines()
    assert lines == [
        "object.skeleton.file id: 1 nodes repeat an id used before (ids 2: 2 times)",
        "object.skeleton.file parent: 1 nodes name a parent id that no node has (ids 4: parent 99)",
        "object.skeleton.file parent: 2 nodes in or below a cycle (ids 5: parent 6, 6: parent 5)",
        "object.skeleton.file joints: 1 nodes with non-finite coordinates (ids 7: [nan, 6, 0])",
        "object.skeleton.file radius: 1 nodes with radius <= 0 or not a number (ids 2: 0)",
    ], lines
    with pytest.raises(ValueError) as e:  # the default policy repairs the radius but not the rest
        repair(sk)
    assert len(str(e.value).splitlines()) == 4


def test_swc_round_trip_keeps_joints_radii_topology_and_labels(tmp_path):
    rng = np.random.default_rng(7)
    n = 200
    parents = np.array([-1] + [int(rng.integers(0, k)) for k in range(1, n)])
    parents[120] = -1  # a second root
    joints = rng.normal(size=(n, 3)) * 1e4 / 3.0  # nanometre-like values, full float64 mantissas
    radii = rng.uniform(0.01, 500.0, n)
    labels = rng.integers(0, 8, n)
    ids = rng.permutation(10 * n)[:n] + 1
    a = from_arrays(joints, radii, parents, labels=labels, ids=ids)
    b = read_swc(write_swc(tmp_path / "a.swc", a))
    c = read_swc(write_swc(tmp_path / "b.swc", b))
    for x, y in ((a, b), (b, c)):
        for name in ("joints", "radii", "parents", "labels", "ids", "parent_ids"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
    np.testing.assert_array_equal(b.joints, joints)  # bit for bit
    text = (tmp_path / "a.swc").read_text().splitlines()
    assert text[0].startswith("#") and len([t for t in text if not t.startswith("#")]) == n


def test_type_colours_follow_the_documented_table():
    got = label_colors(np.array([0, 1, 2, 3, 4, 5, 7]))
    np.testing.assert_array_equal(got[:5], [TYPE_COLORS[k] for k in range(5)])
    np.testing.assert_array_equal(got[5], got[6])
    assert not any(np.array_equal(got[5], TYPE_COLORS[k]) for k in range(5))


def test_bad_lines_are_named_in_one_error(tmp_path):
    with pytest.raises(ValueError, match=r"skeleton\.file: expected 7 numbers a line \(line 2: '2 3 0 1 0 1'; line 3: '3 x 0 2 0 1 2'\)"):
        read_swc(_write(tmp_path, "b.swc", "1 3 0 0 0 1 -1\n2 3 0 1 0 1\n3 x 0 2 0 1 2\n"))


# --- the config and the CLI -------------------------------------------------------------------

NEURON = """# soma, a dendrite with an unknown radius and a duplicate node, an axon
1 1 0 0 0 2 -1
2 3 0 5 0 1 1
3 3 0 10 0 0 2
4 3 0 10 0 0.5 3
5 3 3 14 0 0.5 4
6 2 0 -6 0 0.8 1
"""


def _experiment(tmp_path, skeleton: str, camera: str = "{eye: [0, 2, 20], target: [0, 2, 0], width: 32, height: 24}") -> str:
    p = tmp_path / "exp.yaml"
    p.write_text(f"""
object:
  type: frusta
  skeleton: {skeleton}
camera: {camera}
render: {{progress: false}}
""")
    return str(p)


def test_cli_renders_an_swc_and_reports_the_repairs(tmp_path):
    swc = _write(tmp_path, "neuron.swc", NEURON)
    out = tmp_path / "o"
    assert cli.main(["render", _experiment(tmp_path, f"{{file: {swc}, scale: 0.5}}"), "--out", str(out)]) == 0
    run = json.loads((out / "run.json").read_text())
    rep = run["info"]["repairs"]
    assert rep["default_policy"] is True and rep["policy"]["unknown_radius"] == "parent" and rep["policy"]["merge_zero_length"]
    assert rep["unknown_radius"] == {"count": 1, "ids": [3]}
    assert rep["zero_length_merged"] == {"count": 1, "ids": [4]}
    assert run["info"]["segments"] == 4 and run["info"]["joints"] == 5
    # two joints continue a segment: node 2 in line with the soma's segment, node 3 after a
    # 36.9 degree bend (Eq. 3-5's plane, its pieces within reach)
    assert run["info"]["joint_planes"] == {"eq_3_5": 1, "collinear": 1, "bisector": 0, "perpendicular_caps": 0}
    depth = np.load(out / "depth.npy")
    hit = np.isfinite(depth)
    assert 0.01 < hit.mean() < 0.6
    # scale 0.5: the nearest surface is the soma cone's base, radius 2 * 0.5 at the origin, so no
    # hit is nearer the eye than 20 - 1 along the view axis, and some within 0.5 of it
    assert depth[hit].min() >= 19.0 - 1e-3 and depth[hit].min() < 19.5


@pytest.fixture
def no_compile(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("compiled despite bad input")

    monkeypatch.setattr(executor, "compile_batch_fn", boom)


@pytest.mark.parametrize("skeleton, needle", [
    ("{file: NOPE/missing.swc}", ["object.skeleton.file", "no such file", "missing.swc"]),
    ("{file: DIR/neuron.txt}", ["object.skeleton.file", "cannot tell the format", "neuron.txt"]),
    ("{file: DIR/neuron.txt, format: nodes}", ["object.skeleton.file", "header has no column"]),
    ("{file: DIR/neuron.swc, format: obj}", ["object.skeleton.format", "obj"]),
    ("{file: DIR/neuron.swc, repair: {unknown_radius: error}}", ["object.skeleton.file radius: 2 nodes", "ids 3: 0, 7: -1"]),
    ("{file: DIR/neuron.swc, repair: {unknown_radius: sometimes}}", ["object.skeleton.repair.unknown_radius", "sometimes"]),
    ("{joints: [[0,0,0],[0,1,0]], radii: [1, 1], parents: [-1, 0], repair: {}}", ["object.skeleton", "'repair' applies to a skeleton 'file' only"]),
])
def test_bad_file_settings_are_one_line_and_exit_2(tmp_path, capsys, no_compile, skeleton, needle):
    _write(tmp_path, "neuron.swc", NEURON + "7 3 0 -9 0 -1 6\n")
    _write(tmp_path, "neuron.txt", NEURON)
    exp = _experiment(tmp_path, skeleton.replace("DIR", str(tmp_path)).replace("NOPE", str(tmp_path / "nope")))
    rc = cli.main(["render", exp, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    for n in needle:
        assert n in err[0], (n, err[0])


FOLDS = """# a duplicate node (merged by repair) and an unknown radius (the parent's), then a fold back
10 3 0 0 0 1 -1
20 3 0 10 0 1 10
21 3 0 10 0 1 20
30 3 0 5 0 0 21
"""


@pytest.mark.parametrize("repair, needle", [
    # after repair the nodes are 10, 20, 30 (rows 0, 1, 2): node 30 turns back 180 degrees at 20
    ("", ["object.skeleton.file node id 20 (line 3): object.skeleton.joints[1]: ", "folds back"]),
    # kept, the duplicate node 21 (row 2, line 4) ends a zero-length segment from 20
    (", repair: {merge_zero_length: false}", ["object.skeleton.file node id 21 (line 4): object.skeleton.joints[2]: ",
                                               "zero-length segment 1 -> 2 (node ids 20 -> 21)"]),
])
def test_a_problem_repair_leaves_names_the_file_node_id_and_line(tmp_path, capsys, no_compile, repair, needle):
    swc = _write(tmp_path, "folds.swc", FOLDS)
    rc = cli.main(["render", _experiment(tmp_path, f"{{file: {swc}{repair}}}"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("jskel: error: " + needle[0]) and needle[1] in err[0], err[0]


def test_node_lines_are_the_files_lines(tmp_path):
    csv = _write(tmp_path, "n.csv", "node_id,x,y,z,radius,parent_id\n5,0,0,0,1,-1\n\n6,0,1,0,1,5\n7,0,2,0,1,6\n")
    np.testing.assert_array_equal(read_node_table(csv).lines, [2, 4, 5])
    np.testing.assert_array_equal(read_swc(_write(tmp_path, "f.swc", FOLDS)).lines, [2, 3, 4, 5])
    fixed, _ = repair(read_swc(_write(tmp_path, "f.swc", FOLDS)))
    np.testing.assert_array_equal(fixed.lines, [2, 3, 5])  # node 21 merged away


DATA = Path(__file__).resolve().parent / "data" / "swc"


def _real_swc_files() -> list:
    """Published SWC files to read: the NeuroMorpho.Org reconstructions committed in
    ``tests/data/swc`` (CC BY 4.0; its README names them), plus any given in ``JSKEL_REAL_SWC``
    (paths separated by the OS path separator)."""
    import os

    given = os.environ.get("JSKEL_REAL_SWC", "")
    return sorted(DATA.glob("*.swc")) + [Path(p) for p in given.split(os.pathsep) if p]


def test_published_swc_files_read_as_their_text():
    for path in _real_swc_files():
        ref = np.loadtxt(path, comments="#", ndmin=2)  # the file's own text, parsed by plain NumPy
        sk = read_swc(path)
        assert sk.ids.size == ref.shape[0], path
        np.testing.assert_array_equal(sk.ids, ref[:, 0].astype(np.int64))
        np.testing.assert_array_equal(sk.labels, ref[:, 1].astype(np.int64))
        assert int(np.sum(sk.parents == -1)) == int(np.sum(ref[:, 6] < 0)), path
        np.testing.assert_array_equal(sk.joints.min(0), ref[:, 2:5].min(0))
        np.testing.assert_array_equal(sk.joints.max(0), ref[:, 2:5].max(0))
        np.testing.assert_array_equal(sk.radii, ref[:, 5])
        has_parent = ref[:, 6] >= 0
        assert np.all(np.isin(ref[has_parent, 6], ref[:, 0])), path  # every parent names a node
        np.testing.assert_array_equal(sk.ids[sk.parents[has_parent]], ref[has_parent, 6].astype(np.int64))
        np.testing.assert_array_equal(sk.parent_ids, np.where(ref[:, 6] < 0, -1, ref[:, 6]).astype(np.int64))


def test_an_swc_in_nanometres_far_from_the_origin_is_framed_by_the_camera(tmp_path):
    """``camera: {frame: auto}``: the file's neuron, in nanometres two millimetres from the
    origin, read with ``scale: 0.001``, is seen whole without a hand-placed eye. The target is
    the centre of the joints' boxes grown by their radii (after the repairs: node 3's unknown
    radius takes its parent's), the eye lies along ``view`` at the distance where that box's
    bounding sphere (x 1.05) fills the narrower field of view (here the vertical 40 degrees),
    and no border pixel sees the neuron."""
    rows = [line.split() for line in NEURON.splitlines()[1:]]
    nm = "".join(f"{r[0]} {r[1]} {1000 * float(r[2]) + 2e6} {1000 * float(r[3])} {1000 * float(r[4]) - 5e5} {1000 * float(r[5])} {r[6]}\n"
                 for r in rows)
    swc = _write(tmp_path, "neuron_nm.swc", nm)
    exp = _experiment(tmp_path, f"{{file: {swc}, scale: 0.001}}", "{frame: auto, view: [0, 0, 1], width: 32, height: 24}")
    out = tmp_path / "o"
    assert cli.main(["render", exp, "--out", str(out)]) == 0
    cam = json.loads((out / "run.json").read_text())["config"]["camera"]
    lo = np.array([-2.0, -6.8, -2.0]) + [2000.0, 0.0, -500.0]  # soma radius 2; the axon's end 0.8 below y = -6
    hi = np.array([3.5, 14.5, 2.0]) + [2000.0, 0.0, -500.0]  # the dendrite's tip at (3, 14) of radius 0.5
    centre = 0.5 * (lo + hi)
    dist = 1.05 * 0.5 * np.linalg.norm(hi - lo) / np.sin(np.radians(20.0))
    np.testing.assert_allclose(cam["target"], centre, atol=1e-9)
    np.testing.assert_allclose(cam["eye"], centre + [0.0, 0.0, dist], atol=1e-9)
    hit = np.isfinite(np.load(out / "depth.npy"))
    assert hit.mean() > 0.01
    assert not hit[0].any() and not hit[-1].any() and not hit[:, 0].any() and not hit[:, -1].any()


@pytest.mark.parametrize("camera, needle", [
    ("{frame: auto, eye: [0, 0, 9]}", ["camera", "eye given with frame: auto"]),
    ("{frame: auto, view: [0, 1, 0]}", ["camera", "parallel to up"]),
    ("{frame: sideways}", ["camera.frame", "sideways"]),
])
def test_bad_framing_is_one_line_and_exit_2(tmp_path, capsys, no_compile, camera, needle):
    swc = _write(tmp_path, "neuron.swc", NEURON)
    rc = cli.main(["render", _experiment(tmp_path, f"{{file: {swc}}}", camera), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    for n in needle:
        assert n in err[0], (n, err[0])
