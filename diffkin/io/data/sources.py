"""Arrays read in chunks: :class:`ArraySource` over a memory-mapped ``.npy``, one ``.npz`` entry streamed
from its zip, a CSV read line by line, an in-memory array, or the parts of a sharded data set."""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ...errors import ShapeError
from .formats import DataFileError, _check_finite, _check_numeric, _CsvFile, _npz_member, _read_exact, _skip

__all__ = ["ArraySource"]


def _concat(sources: list, name: str):
    """One source over several (a sharded data set's parts), in order; chunks keep the requested size
    across part boundaries, so chunking matches that of one file."""
    if not sources:
        raise DataFileError(f"{name}: the manifest lists no parts")
    shapes = {tuple(s.shape[1:]) for s in sources}
    if len(shapes) > 1:
        raise ShapeError(f"{name}: its parts hold rows of different shapes {sorted(shapes)}")
    offsets = np.cumsum([0] + [len(s) for s in sources]).tolist()

    def read(start, stop, size):
        pending, held = [], 0
        for src, off in zip(sources, offsets):
            a, b = max(start, off), min(stop, off + len(src))
            if a >= b:
                continue
            for chunk in src.chunks(size, a - off, b - off):
                pending.append(chunk)
                held += chunk.shape[0]
                while held >= size:
                    joined = np.concatenate(pending)
                    yield joined[:size]
                    rest = joined[size:]
                    pending, held = ([rest] if rest.shape[0] else []), rest.shape[0]
        if held:
            yield np.concatenate(pending)

    return ArraySource((offsets[-1], *sources[0].shape[1:]), name, read)


class ArraySource:
    """Rows of one array read in chunks: ``shape`` is the whole array's, ``chunks(size)`` yields float64
    arrays of ``(m, *shape[1:])`` with ``m <= size``, first row ``start``, up to ``stop``."""

    def __init__(self, shape: tuple, name: str, reader):
        self.shape = tuple(shape)
        self.name = name
        self._reader = reader  # (start, stop, size) -> iterator of arrays

    def __len__(self) -> int:
        return self.shape[0]

    def chunks(self, size: int, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        stop = self.shape[0] if stop is None else min(stop, self.shape[0])
        yield from self._reader(start, stop, size)


def _array_source(path: Path, key: str | None, what: str) -> ArraySource:
    """An :class:`ArraySource` for an .npy (memory map), one .npz entry (zip stream) or a whole CSV."""
    if path.suffix == ".npy":
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise DataFileError(f"{path}: cannot read as .npy: {exc}") from None
        _check_numeric(arr.dtype, path)
        if arr.ndim == 0 or arr.shape[0] == 0 or arr.size == 0:
            raise DataFileError(f"{path}: empty array of shape {arr.shape}: no {what}")

        def read(start, stop, size):
            for a in range(start, stop, size):
                yield np.array(arr[a:min(a + size, stop)], dtype=np.float64)

        return ArraySource(arr.shape, str(path), read)
    if path.suffix == ".npz":
        zf, stream, shape, dtype = _npz_member(path, key)
        zf.close()
        _check_numeric(dtype, path, key)
        if len(shape) == 0 or shape[0] == 0 or int(np.prod(shape)) == 0:
            raise DataFileError(f"{path}: entry {key!r} is empty (shape {shape}): no {what}")
        row = int(np.prod(shape[1:], dtype=np.int64))

        def read(start, stop, size):
            zf, stream, shape_, dtype_ = _npz_member(path, key)
            try:
                with zf, stream:
                    _skip(stream, start * row * dtype_.itemsize)
                    for a in range(start, stop, size):
                        m = min(size, stop - a)
                        buf = _read_exact(stream, m * row * dtype_.itemsize, path, key)
                        yield np.frombuffer(buf, dtype=dtype_).reshape(m, *shape_[1:]).astype(np.float64)
            except (zipfile.BadZipFile, OSError, EOFError) as exc:
                raise DataFileError(f"{path}: entry {key!r} is corrupt ({exc})") from None

        return ArraySource(shape, f"{path}[{key}]", read)
    raise AssertionError(path)


def _host_array(t: torch.Tensor) -> np.ndarray:
    """A tensor source as a numpy array: float dtypes numpy lacks (bfloat16, float8) are widened to
    float64 first, as a file's numbers are converted (bool and complex stay, for the data-file rule)."""
    t = t.detach().cpu()
    if t.is_floating_point() and t.dtype not in (torch.float16, torch.float32, torch.float64):
        t = t.double()
    return t.numpy()


def _memory_source(arr: np.ndarray, name: str) -> ArraySource:
    _check_numeric(arr.dtype, name)
    if arr.shape[0] == 0:
        raise DataFileError(f"{name}: empty array of shape {arr.shape}")

    def read(start, stop, size):
        for a in range(start, stop, size):
            yield np.asarray(arr[a:min(a + size, stop)], dtype=np.float64)

    return ArraySource(arr.shape, name, read)


def _csv_source(csv: _CsvFile, cols: list[int] | None) -> ArraySource:
    width = csv.width if cols is None else len(cols)

    def read(start, stop, size):
        a = 0
        for chunk in csv.chunks(size):
            b = a + chunk.shape[0]
            lo, hi = max(start, a), min(stop, b)
            if lo < hi:
                chunk = chunk[lo - a:hi - a]
                yield chunk if cols is None else chunk[:, cols]
            a = b
            if a >= stop:
                return

    return ArraySource((csv.rows, width), str(csv.path), read)


def _finite(src: ArraySource) -> ArraySource:
    inner = src._reader

    def read(start, stop, size):
        a = start
        for chunk in inner(start, stop, size):
            _check_finite(chunk, src.name, a)
            a += chunk.shape[0]
            yield chunk

    return ArraySource(src.shape, src.name, read)


def _zip_sources(pos: ArraySource, quat: ArraySource, name: str) -> ArraySource:
    def read(start, stop, size):
        for p, q in zip(pos.chunks(size, start, stop), quat.chunks(size, start, stop)):
            yield np.concatenate([p, q], axis=-1)

    return ArraySource((*pos.shape[:-1], 7), name, read)
