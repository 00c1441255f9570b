"""Reading and writing batches of joint vectors and poses (``.npy``, ``.npz``, ``.csv``) for the CLI.

Formats
-------
Joint vectors ``(N, n)``: ``.npy`` array, ``.npz`` key ``q``, or ``.csv`` with ``n`` columns (a header line of
names is allowed).

Poses: ``(N, 4, 4)`` homogeneous transforms (``.npy``, or ``.npz`` key ``T``), or rows of 7 numbers
``x y z qw qx qy qz`` (quaternion scalar first), or rows of 3 numbers ``x y z`` (position only), in ``.npy``
or ``.csv``; ``.npz`` may also hold ``position`` ``(N, 3)`` and optionally ``quaternion`` ``(N, 4)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .errors import DiffkinError, ShapeError

__all__ = ["DataFileError", "read_joints", "read_poses", "write_arrays", "read_array"]

_SUFFIXES = (".npy", ".npz", ".csv")


class DataFileError(DiffkinError):
    """A data file is missing, unreadable or has the wrong layout."""


def _check_path(path: str | Path) -> Path:
    path = Path(path)
    if path.suffix not in _SUFFIXES:
        raise DataFileError(
            f"{path}: unsupported file type {path.suffix!r}; use one of {', '.join(_SUFFIXES)}"
        )
    if not path.exists():
        raise DataFileError(f"{path}: no such file")
    return path


def _read_csv(path: Path) -> np.ndarray:
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise DataFileError(f"{path}: empty file")
    try:
        float(lines[0].replace(";", ",").split(",")[0])
    except ValueError:
        lines = lines[1:]  # header row of column names
    rows = []
    for k, ln in enumerate(lines):
        try:
            rows.append([float(v) for v in ln.replace(";", ",").split(",")])
        except ValueError as exc:
            raise DataFileError(f"{path}: row {k + 1}: {exc}") from None
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise DataFileError(f"{path}: rows have different numbers of columns: {sorted(widths)}")
    return np.asarray(rows, dtype=np.float64)


def read_array(path: str | Path, key: str | None = None) -> np.ndarray:
    """Read one array from ``.npy``, ``.csv`` or ``.npz`` (``key`` selects the entry of an ``.npz``)."""
    path = _check_path(path)
    try:
        if path.suffix == ".csv":
            return _read_csv(path)
        if path.suffix == ".npy":
            return np.load(path, allow_pickle=False)
        with np.load(path, allow_pickle=False) as data:
            if key is None or key not in data:
                raise DataFileError(f"{path}: expected an entry {key!r}, found {sorted(data.files)}")
            return data[key]
    except (OSError, ValueError) as exc:
        if isinstance(exc, DiffkinError):
            raise
        raise DataFileError(f"{path}: cannot read: {exc}") from None


def _to_tensor(arr: np.ndarray, dtype, device) -> torch.Tensor:
    if not np.issubdtype(arr.dtype, np.number):
        raise DataFileError(f"expected numbers, got an array of {arr.dtype}")
    t = torch.as_tensor(np.asarray(arr, dtype=np.float64)).to(dtype=dtype, device=device)
    if not bool(torch.isfinite(t).all()):
        raise DataFileError("the data holds NaN or inf values")
    return t


def read_joints(path, n_joints: int, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """Joint vectors ``(N, n)`` from a file; a wrong column count raises :class:`ShapeError`."""
    arr = read_array(path, key="q")
    if arr.ndim == 1 and arr.shape[0] == n_joints:
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != n_joints:
        raise ShapeError(f"{path}: expected joint vectors of shape (N, {n_joints}), got {tuple(arr.shape)}")
    return _to_tensor(arr, dtype, device)


def read_poses(path, dtype=torch.float64, device="cpu") -> tuple[torch.Tensor, bool]:
    """Target poses from a file: ``(T (N, 4, 4), position_only)``.

    Position-only rows ``(N, 3)`` give transforms with identity rotation and ``position_only=True``.
    """
    from .rotations import quaternion_to_matrix

    path = Path(path)
    if path.suffix == ".npz":
        _check_path(path)
        with np.load(path, allow_pickle=False) as data:
            if "T" in data:
                arr = data["T"]
            elif "position" in data:
                pos = data["position"]
                arr = np.concatenate([pos, data["quaternion"]], axis=-1) if "quaternion" in data else pos
            else:
                raise DataFileError(
                    f"{path}: expected an entry 'T' or 'position', found {sorted(data.files)}"
                )
    else:
        arr = read_array(path)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        return _to_tensor(arr, dtype, device), False
    if arr.ndim == 2 and arr.shape[1] in (3, 7):
        t = _to_tensor(arr, dtype, device)
        T = torch.eye(4, dtype=dtype, device=device).repeat(t.shape[0], 1, 1)
        T[:, :3, 3] = t[:, :3]
        if arr.shape[1] == 7:
            quat = t[:, 3:]
            quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            T[:, :3, :3] = quaternion_to_matrix(quat)
        return T, arr.shape[1] == 3
    raise ShapeError(
        f"{path}: expected poses of shape (N, 4, 4), (N, 7) [x y z qw qx qy qz] or (N, 3) [x y z], "
        f"got {tuple(arr.shape)}"
    )


def write_arrays(path: str | Path, columns: dict[str, np.ndarray]) -> Path:
    """Write named arrays: ``.npz`` keeps them all; ``.csv`` flattens each to columns; ``.npy`` the first."""
    path = Path(path)
    if path.suffix not in _SUFFIXES:
        raise DataFileError(
            f"{path}: unsupported output type {path.suffix!r}; use one of {', '.join(_SUFFIXES)}"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(v) for k, v in columns.items()}
    if path.suffix == ".npz":
        np.savez(path, **arrays)
    elif path.suffix == ".npy":
        np.save(path, next(iter(arrays.values())))
    else:
        names, cols = [], []
        for k, v in arrays.items():
            v2 = v.reshape(v.shape[0], -1).astype(np.float64)
            cols.append(v2)
            names += [k] if v2.shape[1] == 1 else [f"{k}_{j}" for j in range(v2.shape[1])]
        np.savetxt(path, np.concatenate(cols, axis=1), delimiter=",", header=",".join(names), comments="")
    return path
