"""Target poses from files and arrays: :class:`PoseSource` (4x4 transforms, ``x y z qw qx qy qz`` rows
or positions, checked by the quaternion rule and the rigidity rule), and the whole-file readers of poses and
calibration measurements."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ...errors import ShapeError
from ...rotations import _quaternion_to_matrix
from .formats import (
    QUATERNION_NORM_TOLERANCE,
    DataFileError,
    _check_path,
    _column_index,
    _CsvFile,
    _is_manifest,
    _manifest_parts,
    _npz_keys,
    _tensor,
)
from .joints import joint_count, read_joints
from .sources import (
    ArraySource,
    _array_source,
    _concat,
    _csv_source,
    _finite,
    _host_array,
    _memory_source,
    _zip_sources,
)

__all__ = ["PoseSource", "open_pose_source", "read_measurements", "read_poses"]


class PoseSource:
    """Target poses read in chunks: ``chunks(size)`` yields float64 ``(m, [K,] 4, 4)`` transforms, checked
    (finite, unit quaternions, rigid transforms); ``position_only`` when the input holds positions only."""

    def __init__(self, rows: ArraySource, layout: str, n_ends: int, single_end: bool, name: str):
        self.rows, self.layout, self.name = rows, layout, name
        self.n_ends, self.single_end = n_ends, single_end
        self.position_only = layout == "position"

    def __len__(self) -> int:
        return len(self.rows)

    def chunks(self, size: int, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        a = start
        for chunk in self.rows.chunks(size, start, stop):
            yield _to_transforms(chunk, self.layout, self.n_ends, self.single_end, self.name, a)
            a += chunk.shape[0]


def _to_transforms(chunk: np.ndarray, layout: str, K: int, single_end: bool, name: str, first: int):
    m = chunk.shape[0]
    if layout == "T":
        from ...transforms import RIGIDITY_TOLERANCE, _nearest_rigid, _transform_deviations

        T = torch.from_numpy(np.ascontiguousarray(chunk.reshape(m, K, 4, 4)))

        def where(index: tuple) -> str:
            return f"{name}: row {first + index[0] + 1}" + ("" if single_end else f", end {index[1] + 1}")

        devs = _transform_deviations(T, name, RIGIDITY_TOLERANCE, where, DataFileError)
        T = _nearest_rigid(T, *devs).numpy()  # the one rule: within it re-orthonormalised
    else:
        width = 3 if layout == "position" else 7
        rows = chunk.reshape(m, K, width)
        T = np.zeros((m, K, 4, 4))
        T[..., :3, 3] = rows[..., :3]
        T[..., 3, 3] = 1.0
        if layout == "position":
            T[..., 0, 0] = T[..., 1, 1] = T[..., 2, 2] = 1.0
        else:
            quat = rows[..., 3:]
            norm = np.linalg.norm(quat, axis=-1)  # (m, K)
            off = np.abs(norm - 1.0)
            bad = np.nonzero(off.max(axis=-1) > QUATERNION_NORM_TOLERANCE)[0]
            if bad.size:
                i = int(bad[0])
                j = int(off[i].argmax())
                raise DataFileError(
                    f"{name}: row {first + i + 1}: quaternion (qw qx qy qz) {quat[i, j].round(6).tolist()} "
                    f"has norm {norm[i, j]:.6g}, not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g}; it is never "
                    "normalised silently); if these rows are joint vectors, they are input for `diffkin fk`"
                )
            # the one encoding of (2.33), the kernels' (float64 here, as the rows are read)
            T[..., :3, :3] = _quaternion_to_matrix(torch.from_numpy(quat / norm[..., None])).numpy()
    return T[:, 0] if single_end else T


def _pose_names(K: int, single_end: bool) -> list[tuple[list[str], list[str]]]:
    """Per end: (position names, quaternion names) of the CSV columns."""
    if single_end:
        return [(["x", "y", "z"], ["qw", "qx", "qy", "qz"])]
    return [([f"{c}_{k + 1}" for c in "xyz"], [f"{c}_{k + 1}" for c in ("qw", "qx", "qy", "qz")])
            for k in range(K)]


def open_pose_source(source, n_ends: int = 1, single_end: bool = True) -> PoseSource:
    """Target poses from a file path or an array / tensor (layouts in the module docstring)."""
    K = n_ends
    lead = () if single_end else (K,)
    if _is_manifest(source):
        parts = [open_pose_source(p, n_ends, single_end) for p in _manifest_parts(source)]
        layouts = {p.layout for p in parts}
        if len(layouts) > 1:
            raise DataFileError(f"{source}: its parts hold different pose layouts {sorted(layouts)}")
        return PoseSource(_concat([p.rows for p in parts], str(source)), parts[0].layout, K, single_end,
                          str(source))
    if isinstance(source, (np.ndarray, torch.Tensor)):
        arr = _host_array(source) if isinstance(source, torch.Tensor) else source
        rows = _memory_source(arr, "targets")
        name = "targets"
    else:
        path = _check_path(source)
        name = str(path)
        if path.suffix == ".csv":
            return _csv_pose_source(path, K, single_end)
        if path.suffix == ".npz":
            keys = _npz_keys(path)
            if "T" in keys:
                rows = _array_source(path, "T", "poses")
            elif "position" in keys:
                pos = _array_source(path, "position", "positions")
                if "quaternion" not in keys:
                    rows = pos
                else:
                    quat = _array_source(path, "quaternion", "quaternions")
                    if quat.shape[0] != pos.shape[0]:
                        raise ShapeError(f"{path}: 'position' has {pos.shape[0]} rows but 'quaternion' "
                                         f"has {quat.shape[0]}")
                    if pos.shape[1:] != (*lead, 3) or quat.shape[1:] != (*lead, 4):
                        raise ShapeError(f"{path}: expected 'position' {('N', *lead, 3)} and 'quaternion' "
                                         f"{('N', *lead, 4)}, got {pos.shape} and {quat.shape}")
                    rows = _zip_sources(pos, quat, name)
            else:
                raise DataFileError(f"{path}: expected an entry 'T' or 'position', found {sorted(keys)}")
        else:
            rows = _array_source(path, None, "poses")
    shape = rows.shape[1:]
    if shape == (*lead, 4, 4):
        layout = "T"
    elif shape == (*lead, 3):
        layout = "position"
    elif shape == (*lead, 7):
        layout = "pose7"
    else:
        lead_s = "".join(f"{d}, " for d in lead)
        raise ShapeError(
            f"{name}: expected poses of shape (N, {lead_s}4, 4), (N, {lead_s}7) [x y z qw qx qy qz] or "
            f"(N, {lead_s}3) [x y z], got {rows.shape}"
        )
    return PoseSource(_finite(rows), layout, K, single_end, name)


def _csv_pose_source(path: Path, K: int, single_end: bool) -> PoseSource:
    csv = _CsvFile(path)
    names = _pose_names(K, single_end)
    if csv.header is None:
        if single_end and csv.width in (3, 7):
            return PoseSource(_finite(_csv_source(csv, None)), "position" if csv.width == 3 else "pose7",
                              K, single_end, str(path))
        raise ShapeError(
            f"{path}: a CSV without a header must have 3 columns (x y z) or 7 (x y z qw qx qy qz), got "
            f"{csv.width}; name the columns in a header row (x,y,z[,qw,qx,qy,qz])"
        )
    h = csv.header
    legacy = (["position_0", "position_1", "position_2"], ["quaternion_0", "quaternion_1", "quaternion_2",
                                                           "quaternion_3"])
    try:
        pos_cols, quat_cols = [], []
        for pn, qn in names:
            p = _column_index(h, pn)
            if p is None and single_end:
                p = _column_index(h, legacy[0])
                qn = legacy[1]
            if p is None:
                raise DataFileError(f"no columns {', '.join(pn)}")
            pos_cols.append(p)
            quat_cols.append(_column_index(h, qn))
    except DataFileError as exc:
        raise DataFileError(
            f"{path}: the header ({', '.join(h)}) must name the target columns x, y, z and, for full poses, "
            f"qw, qx, qy, qz: {exc}"
        ) from None
    if any(q is None for q in quat_cols) and not all(q is None for q in quat_cols):
        raise DataFileError(f"{path}: some end links have quaternion columns and some do not")
    if quat_cols[0] is None:
        cols = [c for p in pos_cols for c in p]
        layout = "position"
    else:
        cols = [c for p, q in zip(pos_cols, quat_cols) for c in p + q]
        layout = "pose7"
    rows = _csv_source(csv, cols)
    if not single_end:
        w = 3 if layout == "position" else 7
        inner = rows._reader
        rows = ArraySource((rows.shape[0], K, w), rows.name,
                           lambda a, b, s: (c.reshape(c.shape[0], K, w) for c in inner(a, b, s)))
    return PoseSource(_finite(rows), layout, K, single_end, str(path))


def read_poses(path, dtype=torch.float64, device="cpu", n_ends: int = 1,
               single_end: bool = True) -> tuple[torch.Tensor, bool]:
    """Target poses from a file: ``(T (N, 4, 4), position_only)`` (layouts and the quaternion rule in the
    module docstring). Position-only rows ``(N, 3)`` give transforms with identity rotation."""
    src = open_pose_source(path, n_ends, single_end)
    return _tensor(np.concatenate(list(src.chunks(1 << 20))), dtype, device), src.position_only


def read_measurements(joints, poses=None, n_joints: int | None = None, dtype=torch.float64,
                      device="cpu") -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Calibration measurements: ``(q (N, n), T (N, 4, 4) or positions (N, 3), position_only)``.

    The one reader of joint readings and measured poses (``diffkin calibrate`` and
    :func:`diffkin.calibration.load_measurements`). With ``poses=None`` both come from ``joints``: an ``.npz``
    with ``q`` and ``T`` (or ``position`` [+ ``quaternion``]), or a ``.csv`` read by its header (``q1..qn``
    and ``x,y,z[,qw,qx,qy,qz]``: ``diffkin fk``'s CSV as it is). ``n_joints``: the robot's joint count; a
    file with another count is refused with a :class:`ShapeError` naming both (None: the file's own count,
    by header / shape). The rigidity rule of the poses is that of :func:`open_pose_source`.
    """
    if n_joints is None:
        n_joints = joint_count(joints)
    q = read_joints(joints, n_joints, dtype=dtype, device=device)
    T, position_only = read_poses(joints if poses is None else poses, dtype=dtype, device=device)
    if T.shape[0] != q.shape[0]:
        raise ShapeError(f"{joints}: {q.shape[0]} joint vectors but {T.shape[0]} measured poses"
                         + ("" if poses is None else f" in {poses}"))
    return q, (T[:, :3, 3].contiguous() if position_only else T), position_only
