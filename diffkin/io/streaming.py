"""Batch FK and IK over inputs of any length, chunk by chunk, with bounded memory (``diffkin fk`` / ``ik``).

Memory is a few chunks' worth whatever N is: ``.npy`` inputs are read through a memory map, ``.npz`` entries
from the zip stream and CSV line by line; ``.npy`` and ``.csv`` outputs are written chunk by chunk (an
``.npz`` output is streamed to one ``.npy`` part per entry and zipped at the end, so it needs twice its size
on disk, not in memory). Random inputs (:class:`~diffkin.io.data.RandomJoints`) are generated per chunk and do
not depend on the chunk size. ``start`` / ``stop`` select a row range of the input (one rank's slice of a
sharded run); the output then holds just those rows.

Outputs (N rows, K end links; the ``.npy`` holds the first entry only):

========= ====================================================================================================
``fk``    ``.npy``: ``T`` ``(N, 4, 4)`` (``(N, K, 4, 4)``) in the chain's dtype. ``.npz``: ``q`` ``(N, n)``,
          ``T``, ``position`` ``(N, [K,] 3)``, ``quaternion`` ``(N, [K,] 4)`` (w, x, y, z).
          ``.csv``: header ``q1..qn,x,y,z,qw,qx,qy,qz`` (``x_1 .. qz_K`` for K end links).
``ik``    ``.npy``: ``q`` ``(N, n)``. ``.npz``: ``q``, ``success`` ``(N,)`` bool, ``position_error`` [m],
          ``orientation_error`` [rad] (NaN for position-only solves: not measured), ``iterations``.
          ``.csv``: the same columns, ``q1..qn,success,position_error,orientation_error,iterations``.
          From :class:`~diffkin.io.data.RandomJoints` also the sampled configurations ``q_sampled``
          ``(N, n)`` and the targets (their FK): ``T_target`` in the ``.npz``; ``q_sampled1..n`` and fk's
          ``x,y,z,qw,qx,qy,qz`` in the ``.csv`` (which therefore reads back as targets).
========= ====================================================================================================
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import DiffkinError
from ..io.data import (
    ArraySource,
    PoseSource,
    RandomJoints,
    open_joint_source,
    open_pose_source,
    open_writer,
)
from ..validation import check_count
from .data.poses import _pose_names

__all__ = ["FK_CHUNK_SIZE", "IK_CHUNK_SIZE", "FKStreamResult", "IKStreamResult", "stream_fk", "stream_ik",
           "combine_ik", "seed_of_chunk"]

FK_CHUNK_SIZE = 262_144
IK_CHUNK_SIZE = 65_536

Progress = Callable[[int, int], None]


@dataclass
class FKStreamResult:
    """What :func:`stream_fk` did: ``count`` poses in ``seconds`` (wall, I/O included), of which
    ``compute_seconds`` in FK; ``output`` the file written (or None)."""

    count: int
    seconds: float
    compute_seconds: float
    output: Path | None


@dataclass
class IKStreamResult:
    """Summary of :func:`stream_ik` over all targets (the per-target results are in ``output``).

    ``position_error`` / ``orientation_error``: ``(median, max)`` over all targets [m] / [rad]
    (``orientation_error`` is None for position-only solves). The maxima are exact; the medians are exact
    up to ``exact_limit`` targets and above it read from a log-spaced histogram (relative error below 0.2 %;
    ``median_approximate`` says which).
    """

    count: int
    successes: int
    position_only: bool
    position_error: tuple[float, float]
    orientation_error: tuple[float, float] | None
    seconds: float
    compute_seconds: float
    output: Path | None
    median_approximate: bool = False
    #: the error statistics behind the medians (``(position, orientation)``), kept to combine ranks' results
    stats: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def failures(self) -> int:
        return self.count - self.successes


def combine_ik(results: list[IKStreamResult]) -> IKStreamResult:
    """One summary of several :func:`stream_ik` results over disjoint targets (the ranks of a sharded run):
    counts and maxima add up exactly, medians are those of all targets together (exact up to the
    statistics' limit, as in one run). ``seconds`` and ``compute_seconds`` are the slowest part's (the parts
    run side by side)."""
    pos, ori = _ErrorStats(results[0].stats[0].exact_limit), _ErrorStats(results[0].stats[0].exact_limit)
    for r in results:
        pos.merge(r.stats[0])
        ori.merge(r.stats[1])
    position_only = results[0].position_only
    return IKStreamResult(
        count=sum(r.count for r in results),
        successes=sum(r.successes for r in results),
        position_only=position_only,
        position_error=(pos.median(), pos.max()),
        orientation_error=None if position_only else (ori.median(), ori.max()),
        seconds=max(r.seconds for r in results),
        compute_seconds=max(r.compute_seconds for r in results),
        output=None,
        median_approximate=pos.approximate,
        stats=(pos, ori),
    )


@dataclass
class _ErrorStats:
    """Median and max of a stream of non-negative errors in bounded memory (exact up to ``exact_limit``
    values, then a histogram with 1000 log-spaced bins per decade)."""

    exact_limit: int = 1 << 24
    _parts: list = field(default_factory=list)
    _n: int = 0
    _max: float = 0.0
    _hist: np.ndarray | None = None
    _zeros: int = 0
    _LO, _HI, _PER_DECADE = -20.0, 4.0, 1000

    def add(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if x.size == 0:
            return
        self._max = max(self._max, float(x.max()))
        self._n += x.size
        if self._hist is None:
            self._parts.append(x.astype(np.float32))
            if self._n > self.exact_limit:
                self._hist = np.zeros(int((self._HI - self._LO) * self._PER_DECADE) + 2, dtype=np.int64)
                parts, self._parts = self._parts, []
                for p in parts:
                    self._bin(p.astype(np.float64))
        else:
            self._bin(x)

    def _bin(self, x: np.ndarray) -> None:
        pos = x[x > 0]
        self._zeros += x.size - pos.size
        idx = np.floor((np.log10(pos) - self._LO) * self._PER_DECADE).astype(np.int64) + 1
        np.add.at(self._hist, np.clip(idx, 0, self._hist.size - 1), 1)

    @property
    def approximate(self) -> bool:
        return self._hist is not None

    def median(self) -> float:
        if self._n == 0:
            return math.nan
        if self._hist is None:
            return float(np.median(np.concatenate(self._parts).astype(np.float64)))
        half = (self._n - 1) / 2
        if self._zeros > half:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self._hist), half - self._zeros, side="right"))
        return float(min(10 ** (self._LO + (k - 0.5) / self._PER_DECADE), self._max))

    def max(self) -> float:
        return self._max if self._n else math.nan

    def merge(self, other: _ErrorStats) -> None:
        """Add the values behind ``other`` (exact values, or its histogram)."""
        if other._n == 0:
            return
        if other._hist is None:
            before = self._max if self._n else -math.inf
            for p in other._parts:
                self.add(p)
            self._max = max(before, other._max)  # the exact maxima, not those of the stored float32 copies
            return
        if self._hist is None:  # switch to the histogram before adding one
            self._hist = np.zeros_like(other._hist)
            parts, self._parts = self._parts, []
            for p in parts:
                self._bin(p.astype(np.float64))
        self._hist += other._hist
        self._zeros += other._zeros
        self._n += other._n
        self._max = max(self._max, other._max)


@contextlib.contextmanager
def _aborting(writer):
    """Remove a half-written output when the streaming fails or is interrupted."""
    try:
        yield
    except BaseException:
        if writer is not None:
            writer.abort()
        raise


def _check_range(n: int, chunk_size: int, start: int, stop: int | None) -> tuple[int, int]:
    check_count(chunk_size, "chunk_size")
    stop = n if stop is None else int(stop)
    if not 0 <= int(start) <= stop <= n:
        raise DiffkinError(f"expected 0 <= start <= stop <= {n} (rows of the input), got [{start}, {stop})")
    if start == stop:
        raise DiffkinError(f"the row range [{start}, {stop}) is empty")
    return int(start), stop


def seed_of_chunk(seed: int, first_row: int) -> int:
    """The seed of the chunk whose first row is ``first_row`` (its rows ``[a, b)``), drawn from ``(seed, a)``
    by :class:`numpy.random.SeedSequence`: one chunking gives the same seeds in any process and shard."""
    return int(np.random.SeedSequence([int(seed), int(first_row)]).generate_state(1)[0])


def _np_dtype(chain) -> np.dtype:
    return np.dtype(str(chain.dtype).removeprefix("torch."))


def stream_fk(
    chain,
    source,
    output: str | Path | None = None,
    *,
    chunk_size: int = FK_CHUNK_SIZE,
    start: int = 0,
    stop: int | None = None,
    progress: Progress | None = None,
) -> FKStreamResult:
    """Forward kinematics of ``source``'s joint vectors ``(N, n)``, chunk by chunk, written to ``output``.

    Args:
        chain: any :class:`~diffkin.chain.KinematicChain` (its dtype and device are used).
        source: a file (``.npy`` / ``.npz`` key ``q`` / ``.csv``, see :mod:`diffkin.io.data`), an array or
            tensor ``(N, n)``, or :class:`~diffkin.io.data.RandomJoints`.
        output: ``.npy`` (poses ``T (N, 4, 4)``, ``(N, K, 4, 4)`` for K end links), ``.npz`` or ``.csv``
            (table in the module docstring); None computes without writing.
        chunk_size: rows per chunk (memory grows with it, not with N).
        start, stop: the rows ``[start, stop)`` of the input (default all).
        progress: called as ``progress(rows_done, rows_total)`` after each chunk.
    """
    from ..rotations import matrix_to_quaternion

    src: ArraySource = open_joint_source(source, chain.n_joints, chain)
    start, stop = _check_range(len(src), chunk_size, start, stop)
    count = stop - start
    K, single = chain.n_ends, chain.single_end
    lead = () if single else (K,)
    dt = _np_dtype(chain)
    writer = None
    if output is not None:
        kind = Path(output).suffix
        qn = [f"q{i + 1}" for i in range(chain.n_joints)]
        pose_names = [c for p, q in _pose_names(K, single) for c in p + q]
        spec = {
            ".npy": {"T": ((*lead, 4, 4), dt, [])},
            ".npz": {"q": ((chain.n_joints,), dt, []), "T": ((*lead, 4, 4), dt, []),
                     "position": ((*lead, 3), dt, []), "quaternion": ((*lead, 4), dt, [])},
            ".csv": {"q": ((chain.n_joints,), np.float64, qn), "pose": ((*lead, 7), np.float64, pose_names)},
        }.get(kind)
        writer = open_writer(output, count, spec or {})
    t0 = time.perf_counter()
    compute = 0.0
    done = 0
    with _aborting(writer):
        for chunk in src.chunks(chunk_size, start, stop):
            q = torch.as_tensor(chunk).to(dtype=chain.dtype, device=chain.device)
            c0 = time.perf_counter()
            with torch.no_grad():
                T = chain.forward_kinematics(q)
                cols = {"T": T}
                if writer is not None and writer.kind != ".npy":
                    quat = matrix_to_quaternion(T[..., :3, :3])
                    cols.update(q=q, position=T[..., :3, 3], quaternion=quat,
                                pose=torch.cat([T[..., :3, 3], quat], -1))
                cols = {k: v.cpu().numpy() for k, v in cols.items()}
            compute += time.perf_counter() - c0
            if writer is not None:
                writer.write(cols)
            done += q.shape[0]
            if progress is not None:
                progress(done, count)
    path = writer.close() if writer is not None else None
    return FKStreamResult(count, time.perf_counter() - t0, compute, path)


def _sampled_spec(chain, suffix: str) -> dict:
    """Output entries of a random IK run (``RandomJoints``): ``q_sampled`` and the targets, ``T_target`` in an
    ``.npz``, the columns of ``diffkin fk``'s CSV (``x,y,z,qw,qx,qy,qz``) in a ``.csv``."""
    n, K, single = chain.n_joints, chain.n_ends, chain.single_end
    lead = () if single else (K,)
    spec = {"q_sampled": ((n,), np.float64, [f"q_sampled{i + 1}" for i in range(n)])}
    if suffix == ".csv":
        names = [c for p, q in _pose_names(K, single) for c in p + q]
        spec["target"] = ((*lead, 7), np.float64, names)
    else:
        spec["T_target"] = ((*lead, 4, 4), _np_dtype(chain), [])
    return spec


def _sampled_columns(T: torch.Tensor, q_sampled: np.ndarray, suffix: str) -> dict:
    from ..rotations import matrix_to_quaternion

    if suffix != ".csv":
        return {"q_sampled": q_sampled, "T_target": T.detach().cpu().numpy()}
    pose = torch.cat((T[..., :3, 3], matrix_to_quaternion(T[..., :3, :3])), dim=-1)
    return {"q_sampled": q_sampled, "target": pose.detach().double().cpu().numpy()}


def stream_ik(
    chain,
    source,
    output: str | Path | None = None,
    *,
    chunk_size: int = IK_CHUNK_SIZE,
    position_only: bool | None = None,
    start: int = 0,
    stop: int | None = None,
    seed: int = 0,
    progress: Progress | None = None,
    exact_limit: int = 1 << 24,
    **solve_options,
) -> IKStreamResult:
    """Inverse kinematics (:func:`diffkin.ik.solve`) of ``source``'s targets, chunk by chunk.

    Args:
        chain: any :class:`~diffkin.chain.KinematicChain`.
        source: a pose file (``.npy`` / ``.npz`` / ``.csv``, layouts and the quaternion rule in
            :mod:`diffkin.io.data`), an array ``(N, 4, 4)`` / ``(N, 7)`` / ``(N, 3)`` (``(N, K, ...)`` for K
            end links), a :class:`~diffkin.io.data.PoseSource`, or :class:`~diffkin.io.data.RandomJoints`
            (targets: the FK of those configurations).
        output: ``.npy`` (``q (N, n)``), ``.npz`` or ``.csv`` (table in the module docstring), or None.
        position_only: solve positions only; None: only when the input holds positions only.
        chunk_size: targets per :func:`~diffkin.ik.solve` call.
        start, stop: the rows ``[start, stop)`` of the input.
        seed: the solver's random restarts of chunk ``[a, b)`` are seeded from ``(seed, a)``: results are
            reproducible for one chunk size but may differ between chunk sizes (the success flags are
            exact either way: each is decided by an FK of the returned ``q``).
        progress: ``progress(targets_done, targets_total)`` after each chunk.
        exact_limit: most targets whose errors are kept for an exact median (4 B each per error).
        solve_options: passed to :func:`~diffkin.ik.solve` (``num_seeds``, tolerances, ...).
    """
    from ..ik import solve

    sampled = isinstance(source, RandomJoints)
    if sampled:
        joints = open_joint_source(source, chain.n_joints, chain)
        src_len, file_position_only = len(joints), False

        def chunks(size, a, b):
            for q in joints.chunks(size, a, b):
                with torch.no_grad():
                    qt = torch.as_tensor(q).to(dtype=chain.dtype, device=chain.device)
                    yield chain.forward_kinematics(qt), q
    else:
        poses = source if isinstance(source, PoseSource) else open_pose_source(
            source, chain.n_ends, chain.single_end)
        src_len, file_position_only = len(poses), poses.position_only

        def chunks(size, a, b):
            for T in poses.chunks(size, a, b):
                yield torch.as_tensor(T).to(dtype=chain.dtype, device=chain.device), None

    if position_only is None:
        position_only = file_position_only
    elif not position_only and file_position_only:
        raise DiffkinError("the targets are positions only (x y z): solve them with position_only=True")
    start, stop = _check_range(src_len, chunk_size, start, stop)
    count = stop - start
    n = chain.n_joints
    writer = None
    if output is not None:
        names = [f"q{i + 1}" for i in range(n)]
        spec = {"q": ((n,), np.float64, names), "success": ((), np.bool_, ["success"]),
                "position_error": ((), np.float64, ["position_error"]),
                "orientation_error": ((), np.float64, ["orientation_error"]),
                "iterations": ((), np.int64, ["iterations"])}
        if sampled:  # the sampled configurations and their FK, the targets: the output checks itself
            spec.update(_sampled_spec(chain, Path(output).suffix))
        if Path(output).suffix == ".npy":
            spec = {"q": ((n,), _np_dtype(chain), [])}
        writer = open_writer(output, count, spec)
    pos_stats, ori_stats = _ErrorStats(exact_limit), _ErrorStats(exact_limit)
    successes = done = 0
    compute = 0.0
    t0 = time.perf_counter()
    with _aborting(writer):
        for T, q_sampled in chunks(chunk_size, start, stop):
            a = start + done
            chunk_seed = seed_of_chunk(seed, a)
            c0 = time.perf_counter()
            with torch.no_grad():
                target = T[..., :3, 3] if position_only else T
                res = solve(chain, target, position_only=position_only, seed=chunk_seed, **solve_options)
                ok = res.success.reshape(-1).cpu().numpy()
                pe = res.position_error.reshape(-1).double().cpu().numpy()
                oe = res.orientation_error.reshape(-1).double().cpu().numpy()
                q = res.q.reshape(-1, n).cpu().numpy()
                it = res.iterations.reshape(-1).cpu().numpy()
            compute += time.perf_counter() - c0
            if position_only:
                oe = np.full_like(pe, np.nan)
            else:
                ori_stats.add(oe)
            pos_stats.add(pe)
            successes += int(ok.sum())
            if writer is not None:
                cols = {"q": q, "success": ok, "position_error": pe, "orientation_error": oe,
                        "iterations": it}
                if sampled:
                    cols.update(_sampled_columns(T, q_sampled, Path(output).suffix))
                writer.write(cols)
            done += ok.shape[0]
            if progress is not None:
                progress(done, count)
    path = writer.close() if writer is not None else None
    return IKStreamResult(
        count=count,
        successes=successes,
        position_only=bool(position_only),
        position_error=(pos_stats.median(), pos_stats.max()),
        orientation_error=None if position_only else (ori_stats.median(), ori_stats.max()),
        seconds=time.perf_counter() - t0,
        compute_seconds=compute,
        output=path,
        median_approximate=pos_stats.approximate,
        stats=(pos_stats, ori_stats),
    )
