"""Sharded batch FK / IK over several processes (``torchrun``), one shard of rows per rank.

``torchrun --nproc-per-node N [--nnodes M --node-rank R --rdzv-endpoint HOST:PORT] -m diffkin.cli fk|ik
--input BIG --output OUT`` runs ``diffkin fk|ik`` once per process; each learns its rank and the world size
from torch.distributed (gloo on CPUs, NCCL when ``--device cuda``: rank r then computes on GPU
``LOCAL_RANK``). The rows of the input are split into contiguous shards on chunk boundaries, so every chunk
is computed exactly as in a single process (same rows, same IK restart seeds): a sharded run equals the
single-process run row for row.

Each rank streams its shard (:mod:`diffkin.streaming`) to its own part file ``OUT`` →
``<stem>.part-00001-of-00004<suffix>``; when all are written, rank 0 writes the manifest
``<stem>.shards.json`` (the parts in order, their rows, what produced them), or with ``merge=True``
(``--merge``) concatenates the parts into ``OUT`` itself and removes them. The manifest is a data set for
everything that reads files (:mod:`diffkin.data_io`, hence ``diffkin ik --input T.shards.json``).

Without torchrun (no ``WORLD_SIZE`` in the environment, or 1) nothing here changes anything: one process,
one output file.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .data_io import (
    MANIFEST_FORMAT,
    MANIFEST_SUFFIX,
    _npz_keys,
    _npz_member,
    _read_exact,
    open_writer,
    read_manifest,
)
from .errors import DiffkinError

__all__ = [
    "MANIFEST_SUFFIX",
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


def merge_parts(output: str | Path, parts: list[Path], step: int = 1 << 18) -> Path:
    """Concatenate part files (all ``.npy``, ``.npz`` or ``.csv`` like ``output``) into ``output``, ``step``
    rows at a time (bounded memory), and remove them. ``.csv`` keeps the first part's header."""
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
        _merge_arrays(output, parts, step)
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


def _merge_arrays(output: Path, parts: list[Path], step: int) -> None:
    opened = [_members(p, output.suffix) for p in parts]
    try:
        first = opened[0]
        total = sum(next(iter(m.values()))[2][0] for m in opened)
        spec = {k: (shape[1:], dtype, []) for k, (_, _, shape, dtype) in first.items()}
        writer = open_writer(output, total, spec)
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
