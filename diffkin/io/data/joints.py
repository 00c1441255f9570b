"""Joint vectors ``(N, n)`` from files, arrays and random draws (:class:`RandomJoints`), chunk by chunk or
whole; a file's joint count is its own (a CSV header's run q1..qn, an array's shape), never cut to fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...errors import ShapeError
from ...validation import check_count
from .formats import DataFileError, _check_path, _CsvFile, _is_manifest, _manifest_parts, _tensor
from .sources import ArraySource, _array_source, _concat, _csv_source, _finite, _host_array, _memory_source

__all__ = ["RandomJoints", "joint_count", "open_joint_source", "read_joints"]


class RandomJoints:
    """``count`` joint vectors drawn uniformly within a chain's sampling ranges (``chain.lower_upper()``;
    quaternions of ball and free joints uniform on S³), float64, by
    :meth:`~diffkin.kernels.configuration.ConfigurationSpace.from_uniform` of float64 uniforms.

    Row ``i`` depends only on ``seed`` and ``i`` (one PCG64 stream advanced to the row), so the samples do
    not depend on the chunk size, and a slice ``[start, stop)`` equals the same rows of the whole set.
    """

    def __init__(self, count: int, seed: int = 0):
        self.count = check_count(count, "count (random samples)")
        self.seed = check_count(seed, "seed", minimum=0)

    def source(self, chain) -> ArraySource:
        from ...sampling import _scalar_ranges

        space = chain.configuration_space
        lo, hi = (t.detach().cpu().double() for t in _scalar_ranges(chain))
        n, nu = chain.nq, space.n_uniform

        def read(start, stop, size):
            for a in range(start, stop, size):
                m = min(size, stop - a)
                bg = np.random.PCG64(self.seed)
                bg.advance(a * nu)  # one 64-bit draw per float64 uniform
                u = torch.from_numpy(np.random.Generator(bg).random((m, nu)))
                yield space.from_uniform(lo, hi, u).numpy()

        return ArraySource((self.count, n), f"random({self.count}, seed={self.seed})", read)


def open_joint_source(source, n_joints: int, chain=None) -> ArraySource:
    """Joint vectors ``(N, n)`` from a file path, an array / tensor, or :class:`RandomJoints` (needs
    ``chain``). Chunks are finite float64 ``(m, n)`` arrays (NaN/inf raise :class:`NonFiniteError`)."""
    if isinstance(source, RandomJoints):
        return source.source(chain)
    if _is_manifest(source):
        return _concat([open_joint_source(p, n_joints, chain) for p in _manifest_parts(source)], str(source))
    if isinstance(source, (np.ndarray, torch.Tensor)):
        arr = _host_array(source) if isinstance(source, torch.Tensor) else source
        if arr.ndim == 1 and arr.shape[0] == n_joints:
            arr = arr[None]
        if arr.ndim != 2 or arr.shape[1] != n_joints:
            raise ShapeError(f"expected joint vectors of shape (N, {n_joints}), got {tuple(arr.shape)}")
        src = _memory_source(arr, "q")
    else:
        path = _check_path(source)
        if path.suffix == ".csv":
            csv = _CsvFile(path)
            cols = None if csv.header is None else _joint_columns(csv.header)
            if cols is not None and len(cols) != n_joints:
                names = f"header {csv.header[cols[0]]}..{csv.header[cols[-1]]}"
                raise ShapeError(_joint_count_message(path, len(cols), n_joints, names))
            if cols is None and csv.width != n_joints:
                raise ShapeError(
                    f"{path}: expected joint vectors of shape (N, {n_joints}) (or a header naming "
                    f"q1..q{n_joints}), got {csv.width} columns"
                )
            src = _csv_source(csv, cols)
        else:
            src = _array_source(path, "q", "joint vectors")
            if len(src.shape) == 1 and src.shape[0] == n_joints:
                raise ShapeError(f"{path}: expected joint vectors of shape (N, {n_joints}), got "
                                 f"{src.shape}; save one configuration as shape (1, {n_joints})")
        if len(src.shape) == 2 and src.shape[1] != n_joints:
            raise ShapeError(_joint_count_message(path, src.shape[1], n_joints, f"shape {src.shape}"))
        if len(src.shape) != 2:
            raise ShapeError(f"{path}: expected joint vectors of shape (N, {n_joints}), got {src.shape}")
    return _finite(src)


#: the header spellings of joint columns: q1..qn, q0..q(n-1), q_0..q_(n-1)
_JOINT_NAMES = ((lambda i: f"q{i + 1}"), (lambda i: f"q{i}"), (lambda i: f"q_{i}"))


def _joint_columns(header: list[str]) -> list[int] | None:
    """Indices of the joint columns a CSV header names (the longest run q1, q2, ... of one spelling), or
    None when it names none: the file's joint count is read from its header, never assumed (q0..q5 is a
    run of six from q0, not of five from q1)."""
    best: list[int] = []
    for name in _JOINT_NAMES:
        k = 0
        while name(k) in header:
            k += 1
        if k > len(best):
            best = [header.index(name(i)) for i in range(k)]
    return best or None


def _joint_count_message(path, found: int, n_joints: int, where: str) -> str:
    return (f"{path}: holds {found} joint values per row ({where}) but the robot has {n_joints} joints; "
            f"expected joint vectors of shape (N, {n_joints})")


def joint_count(path: str | Path) -> int:
    """How many joint values per row a joint file holds: a CSV by its header (q1..qn, see
    :func:`open_joint_source`), an ``.npz`` by its ``q`` entry, an ``.npy`` by its last dimension."""
    if _is_manifest(path):
        return joint_count(_manifest_parts(path)[0])
    path = _check_path(path)
    if path.suffix == ".csv":
        csv = _CsvFile(path)
        cols = None if csv.header is None else _joint_columns(csv.header)
        if cols is None and csv.header is not None:
            raise DataFileError(f"{path}: the header names no joint columns q1..qn")
        return csv.width if cols is None else len(cols)
    shape = _array_source(path, "q", "joint vectors").shape
    if len(shape) != 2:
        raise ShapeError(f"{path}: expected joint vectors of shape (N, n), got {shape}")
    return int(shape[1])


def read_joints(path, n_joints: int, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """Joint vectors ``(N, n)`` from a file; a wrong column count raises :class:`ShapeError`, NaN/inf
    :class:`NonFiniteError`, an empty file :class:`DataFileError`."""
    src = open_joint_source(path, n_joints)
    return _tensor(np.concatenate(list(src.chunks(1 << 20))), dtype, device)
