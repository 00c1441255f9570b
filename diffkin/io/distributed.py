"""Sharded batch FK / IK over several processes (``torchrun``), one shard of rows per rank.

``torchrun --nproc-per-node N [--nnodes M --node-rank R --rdzv-endpoint HOST:PORT] -m diffkin.cli fk|ik
--input BIG --output OUT`` runs ``diffkin fk|ik`` once per process; each learns its rank and the world size
from torch.distributed (gloo on CPUs, NCCL when ``--device cuda``: rank r then computes on GPU
``LOCAL_RANK``). The rows of the input are split into contiguous shards on chunk boundaries, so every chunk
is computed exactly as in a single process (same rows, same IK restart seeds): a sharded run equals the
single-process run row for row.

Each rank streams its shard (:mod:`diffkin.io.streaming`) to its own part file ``OUT`` →
``<stem>.part-00001-of-00004<suffix>``; when all are written, rank 0 writes the manifest
``<stem>.shards.json`` (the parts in order, their rows, what produced them), or with ``merge=True``
(``--merge``) concatenates the parts into ``OUT`` itself and removes them. The manifest is a data set for
everything that reads files (:mod:`diffkin.io.data`, hence ``diffkin ik --input T.shards.json``).

Without torchrun (no ``WORLD_SIZE`` in the environment, or 1) nothing here changes anything: one process,
one output file.

:func:`run_sharded` is the whole orchestration as a Python API (what ``diffkin fk|ik`` calls): this rank's
shard, the gather of every rank's outcome (a failure anywhere stops all ranks with one error and removes the
parts), then on rank 0 the manifest or the merge and the combined summary. The manifest is written here
(:func:`write_manifest`) and read in one place, :func:`diffkin.io.data.read_manifest`.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DiffkinError
from ..io.data import (
    MANIFEST_FORMAT,
    MANIFEST_SUFFIX,
    open_writer,
    read_manifest,
)
from .data.formats import _npz_keys, _npz_member, _read_exact

__all__ = [
    "MANIFEST_SUFFIX",
    "run_sharded",
    "agree",
    "RankInfo",
    "rank_info",
    "init",
    "shard_rows",
    "part_path",
    "manifest_path",
    "write_manifest",
    "read_manifest",
    "merge_parts",
    "gather",
    "barrier",
    "finish",
]



def run_sharded(stream, chain, source, output=None, *, chunk_size: int, merge: bool = False,
                command: str = "", progress=None, device: str | None = None, log=None,
                rows: int | None = None, combine=None, collective: bool = False,
                constants: tuple[str, ...] = (), **options):
    """``stream(chain, source, output, chunk_size=..., **options)``
    (:func:`~diffkin.io.streaming.stream_fk` or :func:`~diffkin.io.streaming.stream_ik`) over every
    rank's shard of ``source``.

    One process: ``stream`` itself. Under torchrun: rank r streams rows :func:`shard_rows` to its part file;
    every rank then learns every outcome (:func:`gather`), so that a failure on any rank raises on all (the
    failing rank its own error, the others a :class:`DiffkinError` naming it) and rank 0 removes the parts
    written: no half data set. On success rank 0 writes the manifest (``command`` recorded in it) or, with
    ``merge``, concatenates the parts into ``output``; it returns the combined summary (counts add up, IK
    medians over all targets, seconds of the slowest rank plus the merge), the other ranks None.
    ``progress(done, total)``: rank 0's shard only. ``device``: joins the process group for it (default the
    chain's device type). ``log(line)``: rank 0's note on the split and the merge.

    Other streams (``diffkin plan``'s): ``rows``, the row count of ``source`` (default: read as fk's joints
    or ik's poses); ``combine(results, written, merge_seconds)``, the summary of every rank's (default: fk's
    or ik's); ``collective``: ``stream`` takes part in collectives (:func:`agree`), so it runs on every rank,
    an empty shard included (it then writes nothing); ``constants``: ``.npz`` entries that are no rows (the
    same in every part), kept once by the merge.
    """
    info = init(device or chain.device.type)
    if not info.sharded:
        return stream(chain, source, output, chunk_size=chunk_size, progress=progress, **options)
    count, rows, res, failure = rows, None, None, None
    try:
        rows, res = _stream_shard(stream, chain, source, output, chunk_size, info,
                                  progress if info.rank == 0 else None, options, count, collective)
    except Exception as exc:  # every rank must reach the gather below, or the others wait for it forever
        failure = exc
    statuses, failed = _outcomes(res, failure)
    if failed:
        if info.rank == 0 and output:  # no half data set: the parts that were written go
            for r in range(info.world):
                part_path(output, r, info.world).unlink(missing_ok=True)
        finish()
        if failure is not None:
            raise failure
        r, msg = failed[0]
        raise DiffkinError(f"rank {r} of {info.world} failed ({msg}); no output written")
    total = _finish_rank0(output, rows, [r for r, _ in statuses if r is not None], info, merge, command,
                          log, combine, constants) if info.rank == 0 else None
    finish()
    return total


def _outcomes(value, failure: BaseException | None) -> tuple[list, list]:
    """Every rank's ``(value, failure message or None)`` and the ``(rank, message)`` of those that failed."""
    statuses = gather((value, None if failure is None else _one_line(failure)))
    return statuses, [(r, msg) for r, (_, msg) in enumerate(statuses) if msg is not None]


def agree(value, failure: BaseException | None = None) -> list:
    """``value`` of every rank, in rank order, on every rank: a step inside a shard's work that every rank
    must reach (``diffkin plan``'s ranks learn the longest motion, so that all parts share one time grid).
    ``failure``: this rank's exception so far (it still takes part); when any rank failed, raises on every
    rank: the failing one its own error, the others a :class:`DiffkinError` naming it. ``[value]`` in one
    process (``failure`` raised)."""
    statuses, failed = _outcomes(value, failure)
    if failure is not None:
        raise failure
    if failed:
        r, msg = failed[0]
        raise DiffkinError(f"rank {r} of {len(statuses)} failed ({msg})")
    return [v for v, _ in statuses]


def _one_line(exc: BaseException) -> str:
    text = f"{exc.filename}: {exc.strerror}" if isinstance(exc, OSError) and exc.filename and exc.strerror \
        else str(exc)
    return " ".join(text.split()) or type(exc).__name__


def _stream_shard(stream, chain, source, output, chunk_size: int, info, progress, options, n, collective):
    """This rank's rows ``[start, stop)`` of the shards, streamed to its part file: ``(rows, result)``."""
    from ..io.data import RandomJoints, open_joint_source, open_pose_source
    from ..io.streaming import stream_fk

    if n is not None:
        pass
    elif isinstance(source, RandomJoints):
        n = source.count
    elif stream is stream_fk:
        n = len(open_joint_source(source, chain.n_joints, chain))
    else:
        n = len(open_pose_source(source, chain.n_ends, chain.single_end))
    rows = [shard_rows(n, chunk_size, r, info.world) for r in range(info.world)]
    start, stop = rows[info.rank]
    part = part_path(output, info.rank, info.world) if output else None
    res = None
    if stop > start or collective:
        res = stream(chain, source, part, chunk_size=chunk_size, start=start, stop=stop, progress=progress,
                     **options)
    return rows, res


def _finish_rank0(output, rows, results: list, info, merge: bool, command: str, log, combine=None,
                  constants: tuple[str, ...] = ()):
    """Rank 0 after every shard succeeded: the manifest or the merged file, and the combined summary."""
    from ..io.streaming import FKStreamResult, combine_ik

    t0 = time.perf_counter()
    written = None
    if output:
        parts = [part_path(output, r, info.world) for r, (a, b) in enumerate(rows) if b > a]
        written = merge_parts(output, parts, constants=constants) if merge else \
            write_manifest(output, info.world, rows, command)
    merge_s = time.perf_counter() - t0
    if combine is not None:
        total = combine(results, written, merge_s)
    elif isinstance(results[0], FKStreamResult):
        total = FKStreamResult(sum(r.count for r in results), max(r.seconds for r in results) + merge_s,
                               max(r.compute_seconds for r in results), written)
    else:
        total = combine_ik(results)
        total.output, total.seconds = written, total.seconds + merge_s
    if log is not None:
        how = (f"; {'parts merged' if merge else 'manifest written'} in {merge_s:.3f} s" if output
               else "; no --output: nothing written")
        log(f"{info.world} processes, rows split on chunk boundaries{how}")
    return total


@dataclass(frozen=True)
class RankInfo:
    """This process's place: ``rank`` of ``world`` processes, ``local_rank`` on its machine."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def sharded(self) -> bool:
        return self.world > 1


def rank_info() -> RankInfo:
    """Rank and world size from the environment torchrun sets (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``)."""
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", str(rank)))
    except ValueError as exc:
        raise DiffkinError(f"bad torchrun environment (RANK / WORLD_SIZE / LOCAL_RANK): {exc}") from None
    if world < 1 or not 0 <= rank < world:
        raise DiffkinError(f"bad torchrun environment: RANK={rank}, WORLD_SIZE={world}")
    return RankInfo(rank, world, local)


def init(device: str = "cpu") -> RankInfo:
    """Join the process group when launched by torchrun with more than one process (gloo for CPUs, NCCL for
    CUDA) and return this rank's :class:`RankInfo`; a single process needs no group."""
    info = rank_info()
    if not info.sharded:
        return info
    import torch
    import torch.distributed as dist

    if not dist.is_initialized():
        if device == "cuda":
            torch.cuda.set_device(info.local_rank)
        dist.init_process_group("nccl" if device == "cuda" else "gloo")
    return info


def barrier() -> None:
    """Wait for every rank (no-op in one process)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def finish() -> None:
    """Wait for every rank, then leave the process group (no-op in one process)."""
    import torch.distributed as dist

    barrier()
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def gather(obj) -> list:
    """``obj`` of every rank, in rank order, on every rank (``[obj]`` in one process)."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return [obj]
    out = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out


def shard_rows(n: int, chunk_size: int, rank: int, world: int) -> tuple[int, int]:
    """Rows ``[start, stop)`` of rank ``rank``: the ``ceil(n / chunk_size)`` chunks split into ``world``
    contiguous runs as even as can be (a rank may get none when there are fewer chunks than ranks)."""
    chunks = -(-n // chunk_size)
    first = rank * chunks // world
    last = (rank + 1) * chunks // world
    return min(first * chunk_size, n), min(last * chunk_size, n)


def part_path(output: str | Path, rank: int, world: int) -> Path:
    """``dir/T.npy`` → ``dir/T.part-00001-of-00004.npy``."""
    output = Path(output)
    return output.with_name(f"{output.stem}.part-{rank:05d}-of-{world:05d}{output.suffix}")


def manifest_path(output: str | Path) -> Path:
    """``dir/T.npy`` → ``dir/T.shards.json``."""
    output = Path(output)
    return output.with_name(output.stem + MANIFEST_SUFFIX)


def write_manifest(output: str | Path, world: int, rows: list[tuple[int, int]], command: str) -> Path:
    """Rank 0's record of a sharded output: the part files (relative to the manifest) and their rows."""
    output = Path(output)
    parts = [{"path": part_path(output, r, world).name, "rows": list(rows[r])}
             for r in range(world) if rows[r][1] > rows[r][0]]
    data = {"format": MANIFEST_FORMAT, "output": output.name, "suffix": output.suffix,
            "rows": sum(b - a for a, b in rows), "parts": parts, "command": command,
            "written": time.strftime("%Y-%m-%dT%H:%M:%S")}
    path = manifest_path(output)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
    return path


def merge_parts(output: str | Path, parts: list[Path], step: int = 1 << 18,
                constants: tuple[str, ...] = ()) -> Path:
    """Concatenate part files (all ``.npy``, ``.npz`` or ``.csv`` like ``output``) into ``output``, ``step``
    rows at a time (bounded memory), and remove them. ``.csv`` keeps the first part's header; ``.npz``
    entries named in ``constants`` (no rows: the same in every part, joint names) are the first part's."""
    output = Path(output)
    tmp = output.with_name(output.name + ".part")
    if output.suffix == ".csv":
        with open(tmp, "w", encoding="utf-8") as dst:
            for i, p in enumerate(parts):
                with open(p, encoding="utf-8") as src:
                    header = src.readline()
                    if i == 0:
                        dst.write(header)
                    while buf := src.read(1 << 24):
                        dst.write(buf)
        os.replace(tmp, output)
    else:
        _merge_arrays(output, parts, step, constants)
    for p in parts:
        p.unlink()
    return output


def _members(part: Path, kind: str) -> dict[str, tuple]:
    """``{key: (close, stream, shape, dtype)}`` of a part: its array (``.npy``) or each entry (``.npz``),
    each stream positioned at its first row."""
    if kind == ".npy":
        f = open(part, "rb")
        version = np.lib.format.read_magic(f)
        fmt = np.lib.format
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, _fortran, dtype = read(f)
        return {"_": (f.close, f, tuple(shape), dtype)}
    out = {}
    for key in _npz_keys(part):
        zf, stream, shape, dtype = _npz_member(part, key)
        out[key] = (zf.close, stream, shape, dtype)
    return out


def _merge_arrays(output: Path, parts: list[Path], step: int, constants: tuple[str, ...] = ()) -> None:
    fixed = {}
    if constants:
        with np.load(parts[0], allow_pickle=False) as z:
            fixed = {k: z[k] for k in constants if k in z.files}
    opened = [_members(p, output.suffix) for p in parts]
    for members in opened:
        for k in fixed:
            members.pop(k)[0]()  # close its stream: written once below
    try:
        first = opened[0]
        total = sum(next(iter(m.values()))[2][0] for m in opened)
        spec = {k: (shape[1:], dtype, []) for k, (_, _, shape, dtype) in first.items()}
        writer = open_writer(output, total, spec, constants=fixed)
        try:
            for part, members in zip(parts, opened):
                n = next(iter(members.values()))[2][0]
                for a in range(0, n, step):
                    m = min(step, n - a)
                    cols = {}
                    for key, (_, stream, shape, dtype) in members.items():
                        size = m * int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
                        buf = _read_exact(stream, size, part, key)
                        cols[key] = np.frombuffer(buf, dtype=dtype).reshape(m, *shape[1:])
                    writer.write(cols)
            writer.close()
        except BaseException:
            writer.abort()
            raise
    finally:
        for members in opened:
            for close, *_ in members.values():
                close()
