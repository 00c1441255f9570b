"""``diffkin fk`` and ``diffkin ik``: batch FK / IK of files or random samples, streamed in chunks
(:mod:`diffkin.io.streaming`) and sharded under ``torchrun`` (:mod:`diffkin.io.distributed`)."""

from __future__ import annotations

import math
import sys

import torch

from ..errors import DiffkinError
from ._common import (
    _check_device,
    _console,
    _load_chain,
    _progress,
    _rate,
    _robot_source,
    _table,
)


# ---------------------------------------------------------------------------------------------- fk
def cmd_fk(args) -> int:
    from ..io.streaming import stream_fk

    chain, source = _stream_input(args, poses=False)
    res = _streamed(args, chain, "FK", stream_fk, source)
    if res is None:  # a rank other than 0 of a sharded run: rank 0 reports
        return 0
    print(
        f"FK of {res.count:,} configurations of '{chain.name}' on {chain.device} "
        f"in {res.compute_seconds:.3f} s "
        f"({_rate(res.count, res.compute_seconds)} configs/s; {res.seconds:.3f} s with I/O)"
        + (f" -> {res.output}" if res.output else "")
    )
    return 0


def _streamed(args, chain, label: str, stream, source, **options):
    """Run ``stream`` (stream_fk / stream_ik) over the input, in this process or, under torchrun, over
    this rank's shard (:func:`diffkin.io.distributed.run_sharded`); returns the summary (the combined one
    on rank 0, None on the other ranks)."""
    from ..io import distributed as dist

    info = dist.init(args.device)
    title = f"{label} (rank 0 of {info.world})" if info.sharded else label
    with _progress(args if info.rank == 0 else _Quiet(), title) as cb:
        return dist.run_sharded(stream, chain, source, args.output, chunk_size=args.chunk_size,
                                merge=args.merge, command=" ".join(sys.argv), progress=cb, device=args.device,
                                log=lambda line: print(line, file=sys.stderr), **options)


class _Quiet:
    no_progress = True


def _stream_input(args, poses: bool):
    """(chain, input) of ``fk`` / ``ik``: the output path checked first, the ranks joined (torchrun), the
    chain loaded, then :func:`_random_source`."""
    from ..io.data import RandomJoints, check_output_path

    if args.output:
        check_output_path(args.output)
    _join_ranks(args)
    chain = _load_chain(args)
    return chain, _random_source(args, chain, RandomJoints, poses)


def _random_source(args, chain, RandomJoints, poses: bool):
    """The input of ``fk`` / ``ik``: ``--input``, or ``--random N`` (collision-free with ``--self-collision``
    / ``--world``: joints, or for ``ik`` their FK poses as the targets). Sets ``args.collision``."""
    from .collision import collision_free_joints, collision_options

    collision, world = collision_options(args, chain, _robot_source(args)[0])
    args.collision = (collision, world, args.margin)
    if not args.random:
        if collision is not None and not poses:
            raise DiffkinError("fk: --self-collision / --world apply to --random samples")
        return args.input
    if collision is None:
        return RandomJoints(args.random, args.seed)
    q = collision_free_joints(chain, args.random, args.seed, args.chunk_size, collision, world, args.margin)
    if not poses:
        return q
    with torch.no_grad():
        T = chain.forward_kinematics(torch.as_tensor(q, dtype=chain.dtype, device=chain.device))
    return T.cpu().double().numpy()


def _join_ranks(args) -> None:
    """Under torchrun: join the process group first, so that ``--device cuda`` is this rank's GPU."""
    from ..io import distributed

    _check_device(args.device)
    distributed.init(args.device)


# ---------------------------------------------------------------------------------------------- ik
def _mm(x: float) -> str:
    return f"{x * 1e3:.4g}"


def _ik_table(chain, res) -> object:
    n, ok = res.count, res.successes
    rate = 100.0 * ok / n
    if ok < n:  # never round a failure away: 99.999 % shows as 99.99 %, not 100.00 %
        rate = math.floor(rate * 100) / 100
    med = "≈" if res.median_approximate else ""
    pos = f"{med}{_mm(res.position_error[0])} / {_mm(res.position_error[1])}"
    ori = "—" if res.orientation_error is None else (
        f"{med}{_mm(res.orientation_error[0])} / {_mm(res.orientation_error[1])}")
    rows = [
        ["targets", f"{n:,}"],
        ["successes", f"{ok:,}"],
        ["failures", f"{n - ok:,}"],
        ["success rate", f"{rate:.2f} %"],
        ["position error median / max [mm]", pos],
        ["orientation error median / max [mrad]", ori],
        ["solve time [s]", f"{res.compute_seconds:.3f} ({res.seconds:.3f} with I/O)"],
        ["solves/s", _rate(n, res.compute_seconds)],
    ]
    title = f"IK on '{chain.name}' ({'position only' if res.position_only else 'full pose'})"
    return _table(title, ["", "value"], rows)


def cmd_ik(args) -> int:
    from ..io.streaming import stream_ik
    from .collision import solve_keywords

    chain, source = _stream_input(args, poses=True)
    res = _streamed(
        args, chain, "IK", stream_ik, source, **solve_keywords(*args.collision),
        position_only=True if args.position_only else None,
        seed=args.seed,
        num_seeds=args.num_seeds,
        position_tolerance=args.position_tolerance,
        orientation_tolerance=args.orientation_tolerance,
    )
    if res is None:  # a rank other than 0 of a sharded run: rank 0 reports
        return 0
    _console().print(_ik_table(chain, res))
    if res.output:
        _console().print(f"wrote {res.output}")
    return 0
