"""Reading and writing batches of joint vectors and poses (``.npy``, ``.npz``, ``.csv``), in one piece or
in chunks of bounded memory.

Joint vectors ``(N, n)``
    ``.npy`` array; ``.npz`` key ``q``; ``.csv`` with ``n`` columns, or with a header row that names them
    ``q1 .. qn`` (other columns, such as ``diffkin fk``'s ``x y z qw qx qy qz``, are then ignored). The
    joint count is the file's (its header's run q1, q2, ..., or its shape): a file of another count than the
    robot's is refused with both counts, never cut to fit.

Poses
    ``.npy``: ``(N, 4, 4)`` homogeneous transforms (``(N, K, 4, 4)`` for K end links), ``(N, 3)`` positions
    or ``(N, 7)`` rows ``x y z qw qx qy qz`` (quaternion scalar first).
    ``.npz``: key ``T``, or ``position`` ``(N, 3)`` and optionally ``quaternion`` ``(N, 4)``.
    ``.csv`` with a header row: columns ``x, y, z`` and, for full poses, ``qw, qx, qy, qz`` (other columns
    ignored, so ``diffkin fk``'s CSV is read as it is); only ``x, y, z`` means position-only targets. For K
    end links the names carry the end's number: ``x_1 .. qz_K``.
    Headerless ``.csv``: 3 columns are ``x y z``, 7 columns ``x y z qw qx qy qz``; any other width is refused.

**Quaternion rule.** A quaternion whose norm differs from 1 by more than ``QUATERNION_NORM_TOLERANCE``
(1e-3) is refused with a :class:`DataFileError` naming its row; it is never normalised silently (a
7-column file of joint vectors is therefore refused by ``diffkin ik``, not read as poses). Within the
tolerance it is normalised. A 4x4 pose must be rigid by the one rule of
:data:`diffkin.transforms.RIGIDITY_TOLERANCE` (max |RᵀR − I|, |det R − 1| and the bottom row's deviation at
most 1e-3): within it the pose is re-orthonormalised, beyond it refused naming the file and row.

Streaming: :func:`open_joint_source` / :func:`open_pose_source` return sources read chunk by chunk
(``.npy`` through a memory map, ``.npz`` member by member from the zip stream, ``.csv`` line by line), and
:func:`open_writer` writes ``.npy`` / ``.csv`` / ``.npz`` outputs chunk by chunk (an ``.npz`` is assembled
from streamed ``.npy`` parts at the end). Outputs are written to ``<name>.part`` and renamed when complete.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..errors import DiffkinError, NonFiniteError, ShapeError
from ..validation import check_count

__all__ = [
    "DataFileError",
    "QUATERNION_NORM_TOLERANCE",
    "ArraySource",
    "PoseSource",
    "RandomJoints",
    "check_output_path",
    "open_joint_source",
    "open_pose_source",
    "open_writer",
    "read_array",
    "joint_count",
    "read_joints",
    "read_measurements",
    "read_poses",
    "write_arrays",
]

_SUFFIXES = (".npy", ".npz", ".csv")
QUATERNION_NORM_TOLERANCE = 1e-3


class DataFileError(DiffkinError):
    """A data file is missing, unreadable or has the wrong layout."""


# ------------------------------------------------------------------------------------------ paths
def _check_path(path: str | Path, suffixes: tuple[str, ...] = _SUFFIXES) -> Path:
    path = Path(path)
    if path.suffix not in suffixes:
        raise DataFileError(
            f"{path}: unsupported file type {path.suffix!r}; use one of {', '.join(suffixes)}"
        )
    if not path.exists():
        raise DataFileError(f"{path}: no such file")
    if path.is_dir():
        raise DataFileError(f"{path}: is a directory, not a data file")
    return path


def check_output_path(path: str | Path, suffixes: tuple[str, ...] = _SUFFIXES) -> Path:
    """Refuse an output path before any work: wrong suffix, an existing directory, or a parent that is (or
    lies under) a regular file."""
    path = Path(path)
    if path.is_dir():
        raise DataFileError(f"{path}: is a directory; give a file name ending in {'/'.join(suffixes)}")
    if path.suffix not in suffixes:
        raise DataFileError(
            f"{path}: unsupported output type {path.suffix!r}; use one of {', '.join(suffixes)}"
        )
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise DataFileError(f"{path}: cannot create it: {parent} is a file, not a directory")
            if not os.access(parent, os.W_OK):
                raise DataFileError(f"{path}: cannot create it: {parent} is not writable")
            break
    return path


# ------------------------------------------------------------------------------------------- CSV
def _split(line: str) -> list[str]:
    return [v.strip().strip('"').strip("'") for v in line.replace(";", ",").split(",")]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _row(fields: list[str], width: int | None, where: str, lineno: int, of: str) -> list[float]:
    """One text row as floats; ``width`` (None: any) the columns it must have (``of``: whose width, for the
    message). :class:`DataFileError` names the line and the first field that is not a number."""
    if width is not None and len(fields) != width:
        raise DataFileError(f"{where}: line {lineno}: {len(fields)} columns, but {of} has {width}")
    try:
        return [float(v) for v in fields]
    except ValueError:
        bad = next(v for v in fields if not _is_number(v))
        raise DataFileError(f"{where}: line {lineno}: not a number: {bad!r}") from None


class _CsvFile:
    """A CSV file read in chunks: header detection, row count, line numbers for errors."""

    def __init__(self, path: Path):
        self.path = path
        self.header: list[str] | None = None
        self.width = 0
        self.rows = 0
        first = None
        with open(path, encoding="utf-8", errors="replace") as f:
            for ln in f:
                s = ln.strip()
                if not s or s.startswith("#"):
                    continue
                if first is None:
                    first = s
                    fields = _split(s)
                    self.width = len(fields)
                    if not all(_is_number(v) for v in fields):
                        self.header = [v.lower() for v in fields]
                        continue
                self.rows += 1
        if first is None or self.rows == 0:
            raise DataFileError(f"{path}: empty file (no data rows)")

    def chunks(self, chunk_size: int) -> Iterator[np.ndarray]:
        header_seen = self.header is None
        lines: list[tuple[int, str]] = []
        with open(self.path, encoding="utf-8", errors="replace") as f:
            for lineno, ln in enumerate(f, 1):
                s = ln.strip()
                if not s or s.startswith("#"):
                    continue
                if not header_seen:
                    header_seen = True
                    continue
                lines.append((lineno, s))
                if len(lines) == chunk_size:
                    yield self._parse(lines)
                    lines = []
        if lines:
            yield self._parse(lines)

    def _parse(self, lines: list[tuple[int, str]]) -> np.ndarray:
        try:
            arr = np.loadtxt([s.replace(";", ",") for _, s in lines], delimiter=",", ndmin=2,
                             dtype=np.float64)
            if arr.shape[1] == self.width:
                return arr
        except ValueError:
            pass
        # quoted fields, or a row to blame
        rows = [_row(_split(s), self.width, str(self.path), lineno, "the file") for lineno, s in lines]
        return np.asarray(rows, dtype=np.float64)


# ------------------------------------------------------------------------------------------ .npz
def _npz_member(path: Path, key: str) -> tuple[zipfile.ZipFile, object, tuple, np.dtype]:
    """An open zip member of an .npz positioned after its .npy header: ``(zipfile, stream, shape, dtype)``."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise DataFileError(f"{path}: not a valid .npz file ({exc})") from None
    names = [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
    if key not in names:
        zf.close()
        raise DataFileError(f"{path}: expected an entry {key!r}, found {sorted(names)}")
    try:
        stream = zf.open(key + ".npy")
        version = np.lib.format.read_magic(stream)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(stream)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        zf.close()
        raise DataFileError(f"{path}: entry {key!r} is not a readable array ({exc})") from None
    if fortran and len(shape) > 1:
        zf.close()
        raise DataFileError(f"{path}: entry {key!r} is Fortran-ordered; save it in C order")
    if dtype.hasobject:
        zf.close()
        raise DataFileError(f"{path}: entry {key!r} holds Python objects, not numbers")
    return zf, stream, tuple(shape), dtype


def _npz_keys(path: Path) -> list[str]:
    try:
        with zipfile.ZipFile(path) as zf:
            return [n[:-4] for n in zf.namelist() if n.endswith(".npy")]
    except (zipfile.BadZipFile, OSError) as exc:
        raise DataFileError(f"{path}: not a valid .npz file ({exc})") from None


# ------------------------------------------------------------------------------------- sources
#: a sharded output's manifest (written by :mod:`diffkin.io.distributed`): ``<stem>.shards.json``
MANIFEST_SUFFIX = ".shards.json"
MANIFEST_FORMAT = "diffkin-shards/1"


def read_manifest(path: str | Path) -> tuple[list[Path], int]:
    """The part files of a manifest, in row order, and the total row count; checks that they exist and
    that their rows tile ``[0, rows)``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataFileError(f"{path}: cannot read the shard manifest: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
        raise DataFileError(f"{path}: not a diffkin shard manifest (expected format {MANIFEST_FORMAT!r})")
    parts, expect = [], 0
    for p in data["parts"]:
        a, b = p["rows"]
        if a != expect:
            raise DataFileError(f"{path}: part {p['path']} starts at row {a}, expected {expect}")
        expect = b
        part = path.parent / p["path"]
        if not part.exists():
            raise DataFileError(f"{path}: part {part} is missing")
        parts.append(part)
    if expect != data["rows"]:
        raise DataFileError(f"{path}: the parts hold {expect} rows, the manifest says {data['rows']}")
    return parts, int(data["rows"])



def _is_manifest(source) -> bool:
    """A sharded output's manifest (``*.shards.json``, written by :mod:`diffkin.io.distributed`)."""
    return isinstance(source, (str, Path)) and str(source).endswith(MANIFEST_SUFFIX)


def _manifest_parts(path) -> list[Path]:
    if not Path(path).exists():
        raise DataFileError(f"{path}: no such file")
    return read_manifest(path)[0]


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


def _skip(stream, nbytes: int) -> None:
    while nbytes > 0:
        got = stream.read(min(nbytes, 1 << 24))
        if not got:
            return
        nbytes -= len(got)


def _read_exact(stream, nbytes: int, path, key) -> bytes:
    buf = io.BytesIO()
    while buf.tell() < nbytes:
        got = stream.read(nbytes - buf.tell())
        if not got:
            raise DataFileError(f"{path}: entry {key!r} is truncated")
        buf.write(got)
    return buf.getvalue()


def _check_numeric(dtype: np.dtype, path, key=None) -> None:
    if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)) or dtype == np.bool_:
        where = f"{path}" + (f" entry {key!r}" if key else "")
        raise DataFileError(f"{where}: expected real numbers, got an array of {dtype}")


def _check_finite(arr: np.ndarray, name: str, first_row: int) -> None:
    if not np.isfinite(arr).all():
        bad = int(np.nonzero(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1))[0][0])
        raise NonFiniteError(f"{name}: row {first_row + bad + 1} holds NaN or inf")


def _column_index(header: list[str], names: list[str]) -> list[int] | None:
    """Indices of ``names`` in ``header``; None if none of them is present; error if only some are."""
    found = [n for n in names if n in header]
    if not found:
        return None
    if len(found) != len(names):
        missing = [n for n in names if n not in header]
        raise DataFileError(f"header has {', '.join(found)} but not {', '.join(missing)}")
    return [header.index(n) for n in names]


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
        from ..sampling import _scalar_ranges

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


def _host_array(t: torch.Tensor) -> np.ndarray:
    """A tensor source as a numpy array: float dtypes numpy lacks (bfloat16, float8) are widened to
    float64 first, as a file's numbers are converted (bool and complex stay, for the data-file rule)."""
    t = t.detach().cpu()
    if t.is_floating_point() and t.dtype not in (torch.float16, torch.float32, torch.float64):
        t = t.double()
    return t.numpy()


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
        from ..transforms import RIGIDITY_TOLERANCE, _nearest_rigid, _transform_deviations

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
            T[..., :3, :3] = _quaternion_to_matrix(quat / norm[..., None])
    return T[:, 0] if single_end else T


def _quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions ``(..., 4)`` (w, x, y, z) (2.33)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


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


def _zip_sources(pos: ArraySource, quat: ArraySource, name: str) -> ArraySource:
    def read(start, stop, size):
        for p, q in zip(pos.chunks(size, start, stop), quat.chunks(size, start, stop)):
            yield np.concatenate([p, q], axis=-1)

    return ArraySource((*pos.shape[:-1], 7), name, read)


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


# --------------------------------------------------------------------------------------- writers
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


# ------------------------------------------------------------------------------- whole-file API
def _read_text(path: Path) -> np.ndarray:
    """A plain-text table ``(N, m)`` (``numpy.savetxt``'s default): one row per line, numbers separated by
    whitespace, commas or semicolons, ``#`` comments and blank lines skipped; every row the same width."""
    rows: list[list[float]] = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            fields = line.split("#", 1)[0].replace(",", " ").replace(";", " ").split()
            if not fields:
                continue
            rows.append(_row(fields, len(rows[0]) if rows else None, str(path), lineno, "the first row"))
    if not rows:
        raise DataFileError(f"{path}: empty file (no data rows)")
    return np.asarray(rows, dtype=np.float64)


def read_array(path: str | Path, key: str | None = None) -> np.ndarray:
    """Read one array from ``.npy``, ``.csv``, ``.npz`` (``key`` selects the entry of an ``.npz``) or a
    plain-text ``.txt`` table (numbers separated by whitespace, commas or semicolons; ``#`` comments), or
    the concatenated parts of a sharded output's manifest (``*.shards.json``,
    :mod:`diffkin.io.distributed`)."""
    if _is_manifest(path):
        return np.concatenate([read_array(p, key) for p in _manifest_parts(path)])
    path = _check_path(path, (*_SUFFIXES, ".txt"))
    try:
        if path.suffix == ".txt":
            return _read_text(path)
        if path.suffix == ".csv":
            csv = _CsvFile(path)
            return np.concatenate(list(csv.chunks(1 << 20)))
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        else:
            with np.load(path, allow_pickle=False) as data:
                if key is None or key not in data:
                    raise DataFileError(f"{path}: expected an entry {key!r}, found {sorted(data.files)}")
                arr = data[key]
    except DiffkinError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise DataFileError(f"{path}: cannot read: {exc}") from None
    _check_numeric(arr.dtype, path, key)
    return arr


def _tensor(arr: np.ndarray, dtype, device) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(arr)).to(dtype=dtype, device=device)


def read_joints(path, n_joints: int, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """Joint vectors ``(N, n)`` from a file; a wrong column count raises :class:`ShapeError`, NaN/inf
    :class:`NonFiniteError`, an empty file :class:`DataFileError`."""
    src = open_joint_source(path, n_joints)
    return _tensor(np.concatenate(list(src.chunks(1 << 20))), dtype, device)


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
