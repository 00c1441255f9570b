"""File layouts of :mod:`diffkin.io.data`: headers, the quaternion rule, chunked readers and writers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffkin.errors import NonFiniteError, ShapeError
from diffkin.io.data import (
    DataFileError,
    check_output_path,
    open_joint_source,
    open_pose_source,
    open_writer,
    read_joints,
    read_poses,
)
from diffkin.rotations import matrix_to_quaternion


def _poses(n=6, seed=0):
    from diffkin import models

    chain = models.load("ur5", dtype=torch.float64)
    T = chain.forward_kinematics(chain.random_configuration(n, generator=torch.Generator().manual_seed(seed)))
    T = T.detach()
    return T.numpy(), matrix_to_quaternion(T[:, :3, :3]).numpy()


def test_csv_read_by_header_in_any_column_order(tmp_path):
    T, quat = _poses()
    cols = {"qz": quat[:, 3], "x": T[:, 0, 3], "extra": np.arange(6.0), "qw": quat[:, 0], "z": T[:, 2, 3],
            "qx": quat[:, 1], "y": T[:, 1, 3], "qy": quat[:, 2]}
    np.savetxt(tmp_path / "p.csv", np.stack(list(cols.values()), 1), delimiter=",", fmt="%.17g",
               header=",".join(cols), comments="")
    T_read, position_only = read_poses(tmp_path / "p.csv")
    assert not position_only
    np.testing.assert_allclose(T_read.numpy(), T, atol=1e-12)
    # the legacy names of an older fk CSV are read too
    legacy = np.concatenate([T[:, :3, 3], quat], 1)
    names = [f"position_{i}" for i in range(3)] + [f"quaternion_{i}" for i in range(4)]
    np.savetxt(tmp_path / "old.csv", legacy, delimiter=",", fmt="%.17g", header=",".join(names), comments="")
    np.testing.assert_allclose(read_poses(tmp_path / "old.csv")[0].numpy(), T, atol=1e-12)


def test_csv_header_without_pose_columns_or_with_half_a_quaternion(tmp_path):
    (tmp_path / "a.csv").write_text("a,b,c\n1,2,3\n")
    with pytest.raises(DataFileError, match="x, y, z"):
        read_poses(tmp_path / "a.csv")
    (tmp_path / "b.csv").write_text("x,y,z,qw,qx,qy\n1,2,3,1,0,0\n")
    with pytest.raises(DataFileError, match="not qz"):
        read_poses(tmp_path / "b.csv")
    np.savetxt(tmp_path / "c.csv", np.zeros((2, 14)), delimiter=",")
    with pytest.raises(ShapeError, match="3 columns .* or 7 .* got 14"):
        read_poses(tmp_path / "c.csv")


def test_headerless_csv_widths(tmp_path):
    T, quat = _poses()
    np.savetxt(tmp_path / "p3.csv", T[:, :3, 3], delimiter=",", fmt="%.17g")
    T3, pos_only = read_poses(tmp_path / "p3.csv")
    assert pos_only and np.allclose(T3[:, :3, 3].numpy(), T[:, :3, 3])
    assert np.allclose(T3[:, :3, :3], np.eye(3))
    np.savetxt(tmp_path / "p7.csv", np.concatenate([T[:, :3, 3], quat], 1), delimiter=",", fmt="%.17g")
    np.testing.assert_allclose(read_poses(tmp_path / "p7.csv")[0].numpy(), T, atol=1e-12)


def test_quaternion_rule_names_the_row_and_never_normalises_silently(tmp_path):
    T, quat = _poses(5)
    rows = np.concatenate([T[:, :3, 3], quat], 1)
    rows[3, 3:] *= 1.01
    (tmp_path / "p.csv").write_text("# comment\nx,y,z,qw,qx,qy,qz\n" + "\n".join(
        ",".join(f"{v:.17g}" for v in r) for r in rows) + "\n")
    with pytest.raises(DataFileError, match=r"row 4: .*norm 1\.01"):
        read_poses(tmp_path / "p.csv")
    np.savez(tmp_path / "p.npz", position=rows[:, :3], quaternion=rows[:, 3:])
    with pytest.raises(DataFileError, match="row 4"):
        read_poses(tmp_path / "p.npz")
    rows[3, 3:] *= 1.0005 / 1.01  # within 1e-3: normalised
    np.save(tmp_path / "p.npy", rows)
    np.testing.assert_allclose(read_poses(tmp_path / "p.npy")[0].numpy(), T, atol=1e-12)


def test_transforms_must_be_rigid(tmp_path):
    T, _ = _poses(4)
    T = T.copy()
    T[2, :3, :3] *= 1.01
    np.save(tmp_path / "T.npy", T)
    with pytest.raises(DataFileError, match="row 3 is not a rigid transform"):
        read_poses(tmp_path / "T.npy")


def test_non_finite_and_malformed_rows_are_named(tmp_path):
    (tmp_path / "q.csv").write_text("q1,q2,q3\n0,0,0\n\n1,2,nan\n")
    with pytest.raises(NonFiniteError, match="row 2"):
        read_joints(tmp_path / "q.csv", 3)
    (tmp_path / "r.csv").write_text("0,0,0\n1,2\n")
    with pytest.raises(DataFileError, match="line 2: 2 columns"):
        read_joints(tmp_path / "r.csv", 3)
    (tmp_path / "s.csv").write_text("0,0,0\n1,2,abc\n")
    with pytest.raises(DataFileError, match="line 2: not a number: 'abc'"):
        read_joints(tmp_path / "s.csv", 3)
    (tmp_path / "e.csv").write_text("q1,q2,q3\n")
    with pytest.raises(DataFileError, match="empty"):
        read_joints(tmp_path / "e.csv", 3)


def test_joint_csv_with_named_columns_among_others(tmp_path):
    (tmp_path / "fk.csv").write_text("x,q2,q1,y\n9,2,1,9\n9,4,3,9\n")
    np.testing.assert_array_equal(read_joints(tmp_path / "fk.csv", 2).numpy(), [[1, 2], [3, 4]])
    with pytest.raises(ShapeError, match=r"\(N, 3\)"):
        read_joints(tmp_path / "fk.csv", 3)


def test_npz_entries_are_streamed_in_chunks(tmp_path):
    q = np.arange(70.0).reshape(10, 7)
    np.savez_compressed(tmp_path / "q.npz", q=q.astype(np.float32), other=np.zeros(3))
    src = open_joint_source(tmp_path / "q.npz", 7)
    chunks = list(src.chunks(3))
    assert [c.shape[0] for c in chunks] == [3, 3, 3, 1] and chunks[0].dtype == np.float64
    np.testing.assert_array_equal(np.concatenate(chunks), q)
    np.testing.assert_array_equal(np.concatenate(list(src.chunks(4, start=2, stop=9))), q[2:9])
    with pytest.raises(DataFileError, match="expected an entry 'q'"):
        open_joint_source(_npz(tmp_path, x=q), 7)
    with pytest.raises(DataFileError, match="real numbers"):
        open_joint_source(_npz(tmp_path, q=q.astype(complex)), 7)


def _npz(tmp_path, **arrays):
    path = tmp_path / "x.npz"
    np.savez(path, **arrays)
    return path


def test_pose_source_multi_end_layout(tmp_path):
    T, quat = _poses(6)
    TK = np.stack([T, T[::-1]], 1)  # (N, 2, 4, 4)
    np.save(tmp_path / "TK.npy", TK)
    src = open_pose_source(tmp_path / "TK.npy", n_ends=2, single_end=False)
    np.testing.assert_allclose(np.concatenate(list(src.chunks(4))), TK)
    with pytest.raises(ShapeError, match=r"\(N, 3, 4, 4\).*got \(6, 2, 4, 4\)"):
        open_pose_source(tmp_path / "TK.npy", n_ends=3, single_end=False)


def test_writers_and_output_checks(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(DataFileError, match="is a file"):
        check_output_path(tmp_path / "f" / "out.npy")
    with pytest.raises(DataFileError, match="unsupported"):
        check_output_path(tmp_path / "out.txt")
    spec = {"a": ((2,), np.float32, ["a1", "a2"]), "b": ((), np.bool_, ["b"])}
    for suffix in (".npy", ".npz", ".csv"):
        w = open_writer(tmp_path / f"o{suffix}", 5, spec)
        w.write({"a": np.ones((3, 2)), "b": np.array([1, 0, 1], bool)})
        w.write({"a": 2 * np.ones((2, 2)), "b": np.array([0, 0], bool)})
        w.close()
    a = np.load(tmp_path / "o.npy")
    assert a.dtype == np.float32 and a.shape == (5, 2) and a[3:].tolist() == [[2, 2], [2, 2]]
    with np.load(tmp_path / "o.npz") as d:
        assert d["b"].tolist() == [True, False, True, False, False] and d["a"].shape == (5, 2)
    assert (tmp_path / "o.csv").read_text().splitlines()[:2] == ["a1,a2,b", "1,1,1"]
    # too few rows: an error, and no partial file left behind
    w = open_writer(tmp_path / "short.npz", 5, spec)
    w.write({"a": np.ones((1, 2)), "b": np.array([1], bool)})
    with pytest.raises(DataFileError, match="wrote 1 rows, expected 5"):
        w.close()
    w.abort()
    assert not list(tmp_path.glob("short*"))


def test_quoted_and_semicolon_csv(tmp_path):
    (tmp_path / "q.csv").write_text('"q1";"q2"\n"1.5";"2"\n3;4\n')
    np.testing.assert_array_equal(read_joints(tmp_path / "q.csv", 2).numpy(), [[1.5, 2], [3, 4]])
