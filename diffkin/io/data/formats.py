"""The file formats under :mod:`diffkin.io.data`: the error type, path checks, CSV and ``.npz`` reading
(header detection, line numbers, zip members read after their ``.npy`` header), shard manifests, the numeric
and finiteness checks, and :func:`read_array` of one whole array."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ...errors import DiffkinError, NonFiniteError

__all__ = ["DataFileError", "QUATERNION_NORM_TOLERANCE", "check_output_path", "read_array", "read_manifest"]


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
