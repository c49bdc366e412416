"""TreeQSM cylinder tables read into skeletons: TreeQSM's own text export (with and without its
header), named-column tables (0- and 1-based parents, axis or end columns), every bad cylinder
in one error, and the format chosen by the config. Expected joints, radii and parents are
written here from the cylinders' closed forms (end = start + length * axis)."""

from __future__ import annotations

import numpy as np
import pytest

from jskel.frusta._config import SkeletonConfig
from jskel.frusta._edits import frusta_from_skeleton, skeleton_and_repairs
from jskel.skeletons import format_of, load, read_qsm

# four cylinders: a trunk (1), its extension bending 36.87 degrees (2), a branch starting on the
# trunk's surface half way up (3, not at the trunk's end) and the branch's extension (4)
CYL = [  # radius, length, start, axis, parent (1-based, 0 none), branch order
    (0.3, 2.0, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0, 0),
    (0.25, 1.5, (0.0, 0.0, 2.0), (0.6, 0.0, 0.8), 1, 0),
    (0.1, 1.0, (0.3, 0.0, 1.0), (0.0, 1.0, 0.0), 1, 1),
    (0.08, 0.5, (0.3, 1.0, 1.0), (0.0, 0.0, 1.0), 3, 1),
]
# cylinder ends are joints 1..4 (ids = cylinder numbers); the trunk and the branch start at
# joints of their own (ids 4 + 1 and 4 + 3), roots with their cylinder's radius
JOINTS = np.array([[0, 0, 2], [0.9, 0, 3.2], [0.3, 1, 1], [0.3, 1, 1.5], [0, 0, 0], [0.3, 0, 1]], np.float64)
RADII = np.array([0.3, 0.25, 0.1, 0.08, 0.3, 0.1])
PARENTS = np.array([4, 0, 5, 2, -1, -1])
IDS = np.array([1, 2, 3, 4, 5, 7])
LABELS = np.array([0, 0, 1, 1, 0, 1])
TREEQSM_HEADER = ["radius (m)", "length (m)", "start_point", "axis_direction", "parent", "extension", "branch",
                  "branch_order", "position_in_branch", "mad", "SurfCov", "added", "UnmodRadius (m)"]


def _treeqsm_rows(extra: int) -> list[list[float]]:
    """TreeQSM's columns: radius length start axis parent extension branch order, then ``extra``
    more (position_in_branch, mad, SurfCov, added, UnmodRadius in version 1.1.0)."""
    return [[r, le, *s, *a, p, 0, 1 + o, o] + [0.5] * extra for r, le, s, a, p, o in CYL]


def _write(tmp_path, name, lines):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _check(sk):
    np.testing.assert_allclose(sk.joints, JOINTS, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sk.radii, RADII)
    np.testing.assert_array_equal(sk.parents, PARENTS)
    np.testing.assert_array_equal(sk.ids, IDS)
    np.testing.assert_array_equal(sk.parent_ids, np.where(PARENTS >= 0, IDS[np.maximum(PARENTS, 0)], -1))


def test_treeqsm_export_with_its_header(tmp_path):
    # save_model_text.m 1.1.0: 13 tab-separated names over 17 columns, %g numbers
    rows = ["\t".join(f"{x:g}" for x in r) for r in _treeqsm_rows(5)]
    sk = read_qsm(_write(tmp_path, "cylinder_tree.txt", ["\t".join(TREEQSM_HEADER)] + rows))
    _check(sk)
    np.testing.assert_array_equal(sk.labels, LABELS)
    np.testing.assert_array_equal(sk.lines, [2, 3, 4, 5, 2, 4])  # a joint's line is its cylinder's


def test_treeqsm_headerless_and_short_tables(tmp_path):
    # version 1.0.0 wrote 15 columns and no header; nine columns carry no branch order
    sk = read_qsm(_write(tmp_path, "a.txt", [" ".join(map(repr, r)) for r in _treeqsm_rows(3)]))
    _check(sk)
    np.testing.assert_array_equal(sk.labels, LABELS)
    sk = read_qsm(_write(tmp_path, "b.txt", [" ".join(map(repr, r[:9])) for r in _treeqsm_rows(0)]))
    _check(sk)
    np.testing.assert_array_equal(sk.labels, 0)


def test_named_columns_zero_based_parents_and_end_points(tmp_path):
    head = "SX, sy, sz, Radius, ax, ay, az, Length, parent, branch_order"
    rows = [", ".join(map(repr, [*s, r, *a, le, p - 1, o])) for r, le, s, a, p, o in CYL]
    _check(read_qsm(_write(tmp_path, "c.csv", [head] + rows)))
    # end points instead of axis and length; parents 1-based (no negative parent)
    ends = {k + 1: [float(x) for x in JOINTS[k]] for k in range(4)}
    head = "radius start_x start_y start_z end_x end_y end_z parent"
    rows = [" ".join(map(repr, [r, *s, *ends[k + 1], p])) for k, (r, le, s, a, p, o) in enumerate(CYL)]
    _check(read_qsm(_write(tmp_path, "d.txt", [head] + rows)))


def test_rounded_axis_is_normalised(tmp_path):
    # TreeQSM rounds axes to 1e-4: (0.7071, 0, 0.7071) has length 0.99999 and is normalised
    line = "0.2 2 1 2 3 0.7071 0 0.7071 0"
    sk = read_qsm(_write(tmp_path, "e.txt", [line]))
    np.testing.assert_allclose(sk.joints[0], [1 + np.sqrt(2), 2, 3 + np.sqrt(2)], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sk.parents, [1, -1])


def test_an_extension_continues_its_parent_across_treeqsms_gap(tmp_path):
    # cylinder 2 starts 0.6 parent radii across the axis from cylinder 1's end (TreeQSM fits
    # cylinders one by one); with TreeQSM's extension column naming it (1 -> 2) it starts at
    # cylinder 1's end joint; without the column, or 5 radii away, it is a cylinder of its own
    def table(offset, extension=True):
        rows = [[0.5, 2, 0, 0, 0, 0, 0, 1, 0, 2], [0.4, 1, offset, 0, 2, 0, 0, 1, 1, 0]]
        return [" ".join(map(str, r if extension else r[:9])) for r in rows]

    sk = read_qsm(_write(tmp_path, "x.txt", table(0.3)))
    np.testing.assert_array_equal(sk.joints, [[0, 0, 2], [0.3, 0, 3], [0, 0, 0]])
    np.testing.assert_array_equal(sk.parents, [2, 0, -1])
    np.testing.assert_array_equal(sk.radii, [0.5, 0.4, 0.5])
    for lines in (table(0.3, extension=False), table(2.5)):
        sk = read_qsm(_write(tmp_path, "y.txt", lines))
        np.testing.assert_array_equal(sk.parents, [2, 3, -1, -1])
        np.testing.assert_array_equal(sk.ids, [1, 2, 3, 4])
        np.testing.assert_array_equal(sk.joints[3], [float(lines[1].split()[2]), 0, 2])


def test_every_bad_cylinder_in_one_error(tmp_path):
    good = "0.2 1 0 0 0 0 0 1 0"
    lines = [good,
             "0 1 0 0 1 0 0 1 1",  # row 2: radius 0
             "0.1 -1 0 0 2 0 0 1 2",  # row 3: length -1
             "0.1 1 0 0 3 1 1 0 3",  # row 4: axis of length sqrt(2)
             "0.1 1 0 0 4 0 0 1 9",  # row 5: parent 9 of 8 cylinders
             "0.1 1 0 0 5 0 0 1 6",  # row 6: its own parent
             "0.1 1 0 nan 6 0 0 1 6",  # row 7: non-finite
             "-0.5 1 0 0 7 0 0 1 7"]  # row 8: radius -0.5
    with pytest.raises(ValueError) as err:
        read_qsm(_write(tmp_path, "bad.txt", lines))
    msg = str(err.value).splitlines()
    assert len(msg) == 5, msg
    assert msg[0] == "skeleton.file numbers: 1 cylinders (row 7 (line 7): non-finite)"
    assert msg[1] == "skeleton.file radius: 2 cylinders (row 2 (line 2): 0 <= 0, row 8 (line 8): -0.5 <= 0)"
    assert msg[2] == "skeleton.file length: 1 cylinders (row 3 (line 3): -1 <= 0)"
    assert msg[3] == f"skeleton.file axis: 1 cylinders (row 4 (line 4): length {np.sqrt(2):.6g}, not 1)"
    assert msg[4] == "skeleton.file parent (1-based, 0 none, 8 cylinders): 2 cylinders (row 5 (line 5): 9, row 6 (line 6): 6)"


def test_many_bad_radii_count_and_first_rows(tmp_path):
    lines = [f"{0.0 if k % 2 else 0.1} 1 0 0 {k} 0 0 1 {k}" for k in range(20)]
    with pytest.raises(ValueError, match=r"skeleton.file radius: 10 cylinders \(row 2 \(line 2\): 0 <= 0, "
                                         r"row 4 .*row 10 \(line 10\): 0 <= 0, \.\.\.\)"):
        read_qsm(_write(tmp_path, "bad.txt", lines))


def test_header_without_needed_columns_names_them(tmp_path):
    with pytest.raises(ValueError, match=r"no column for start0, start1, start2, axis0, axis1, axis2"):
        read_qsm(_write(tmp_path, "h.csv", ["radius,length,parent", "1,1,0"]))


def test_config_reads_a_treeqsm_file_by_name_and_builds(tmp_path):
    rows = ["\t".join(f"{x:g}" for x in r) for r in _treeqsm_rows(5)]
    path = _write(tmp_path, "cylinder_oak.txt", ["\t".join(TREEQSM_HEADER)] + rows)
    assert format_of(path) == "qsm"
    assert format_of(tmp_path / "other.txt", "qsm") == "qsm"
    with pytest.raises(ValueError, match="cannot tell the format"):
        format_of(tmp_path / "other.txt")
    sk, report = load(path)
    _check(sk)
    assert all(v["count"] == 0 for v in report.values()), report
    j, r, p, colors, repairs = skeleton_and_repairs(SkeletonConfig(file=str(path), format="qsm", scale=2.0))
    np.testing.assert_allclose(j, 2.0 * JOINTS, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(r, 2.0 * RADII)
    np.testing.assert_array_equal(p, PARENTS)
    assert colors is not None and repairs["file"] == str(path)
    arrays, topo, info = frusta_from_skeleton(j, r, p)
    assert np.asarray(arrays.h).shape[0] >= 4 and topo.seg_end.shape[0] == 4  # one frustum per cylinder
