"""Outputs written chunk by chunk (:class:`Writer`: ``.npy``, ``.npz`` assembled from streamed parts,
``.csv``; ``<name>.part`` renamed when complete) and whole (:func:`write_arrays`)."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from ...errors import ShapeError
from .formats import DataFileError, check_output_path

__all__ = ["Writer", "open_writer", "write_arrays"]


class _NpyWriter:
    """One array ``(N, *row_shape)`` written row-chunk by row-chunk after its header (no memory map: the
    data go through the page cache, not the process's memory)."""

    def __init__(self, path: Path, shape: tuple, dtype):
        self.path, self.shape, self.dtype = path, tuple(shape), np.dtype(dtype)
        self.f = open(path, "wb")
        header = {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False,
                  "shape": self.shape}
        np.lib.format.write_array_header_1_0(self.f, header)
        self.rows = 0

    def write(self, arr: np.ndarray) -> None:
        arr = np.ascontiguousarray(arr, dtype=self.dtype)
        if arr.shape[1:] != self.shape[1:]:
            raise ShapeError(f"{self.path}: rows of shape {arr.shape[1:]}, expected {self.shape[1:]}")
        self.f.write(memoryview(arr).cast("B"))
        self.rows += arr.shape[0]

    def close(self) -> None:
        self.f.close()
        if self.rows != self.shape[0]:
            raise DataFileError(f"{self.path}: wrote {self.rows} rows, expected {self.shape[0]}")


class Writer:
    """Writes named columns chunk by chunk to ``.npy`` (the first column only), ``.npz`` (all) or ``.csv``
    (all, flattened, with a header row); ``close()`` renames ``<path>.part`` to ``path``, ``abort()`` removes
    it. ``spec`` maps names to ``(row_shape, dtype, csv_names)``; ``constants``: ``.npz`` entries that are no
    rows (joint names), written whole (ignored by ``.npy`` and ``.csv``)."""

    def __init__(self, path: str | Path, count: int, spec: dict[str, tuple],
                 constants: dict[str, np.ndarray] | None = None):
        self.constants = dict(constants or {})
        self.path = check_output_path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.part = self.path.with_name(self.path.name + ".part")
        self.count, self.spec, self.kind = count, spec, self.path.suffix
        self._parts: dict[str, tuple[Path, _NpyWriter]] = {}
        if self.kind == ".npy":
            key = next(iter(spec))
            shape, dtype, _ = spec[key]
            self._npy = _NpyWriter(self.part, (count, *shape), dtype)
            self._key = key
        elif self.kind == ".npz":
            for key, (shape, dtype, _) in spec.items():
                p = self.path.with_name(f"{self.path.name}.{key}.part.npy")
                self._parts[key] = (p, _NpyWriter(p, (count, *shape), dtype))
        else:
            self._csv = open(self.part, "w", encoding="utf-8")
            self._csv.write(",".join(nm for _, _, names in spec.values() for nm in names) + "\n")

    def write(self, columns: dict[str, np.ndarray]) -> None:
        if self.kind == ".npy":
            self._npy.write(columns[self._key])
        elif self.kind == ".npz":
            for key, (_, w) in self._parts.items():
                w.write(columns[key])
        else:
            flat = [np.asarray(columns[k]).reshape(len(columns[k]), -1).astype(np.float64) for k in self.spec]
            np.savetxt(self._csv, np.concatenate(flat, axis=1), delimiter=",", fmt="%.17g")

    def close(self) -> Path:
        if self.kind == ".npy":
            self._npy.close()
        elif self.kind == ".npz":
            for _, w in self._parts.values():
                w.close()
            with zipfile.ZipFile(self.part, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
                for key, (p, _) in self._parts.items():
                    with open(p, "rb") as src, zf.open(key + ".npy", "w", force_zip64=True) as dst:
                        while buf := src.read(1 << 24):
                            dst.write(buf)
                    p.unlink()
                for key, arr in self.constants.items():
                    with zf.open(key + ".npy", "w", force_zip64=True) as dst:
                        np.lib.format.write_array(dst, np.asarray(arr), allow_pickle=False)
        else:
            self._csv.close()
        os.replace(self.part, self.path)
        return self.path

    def abort(self) -> None:
        for f in (getattr(self, "_npy", None) and self._npy.f, getattr(self, "_csv", None)):
            if f is not None:
                f.close()
        for p, w in self._parts.values():
            w.f.close()
            p.unlink(missing_ok=True)
        self.part.unlink(missing_ok=True)


def open_writer(path: str | Path, count: int, spec: dict[str, tuple],
                constants: dict[str, np.ndarray] | None = None) -> Writer:
    """A :class:`Writer` of ``count`` rows for ``spec`` (see there)."""
    return Writer(path, count, spec, constants)


def write_arrays(path: str | Path, columns: dict[str, np.ndarray]) -> Path:
    """Write named arrays: ``.npz`` keeps them all; ``.csv`` flattens each to columns; ``.npy`` the first."""
    path = check_output_path(path)
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
