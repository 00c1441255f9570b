"""Forward-kinematics speed: diffkin vs pytorch-kinematics on the same Panda, in one run.

    python -m benchmarks.bench_fk [--batch 1 1000 100000] [--dtype float32 float64] [--threads 1]
                                  [--device cpu] [--compile] [--no-memory] [--no-peers] [--quick]

diffkin: ``models.load("panda")`` (modified DH, flange); pytorch-kinematics 0.10:
``build_serial_chain_from_urdf(panda.urdf, "panda_link8")`` of the bundled URDF (the same frames). Both get
the same random joint batch, end-effector pose only, under ``torch.no_grad()``. Rows: seconds per call
(median, see :mod:`benchmarks.common`), configurations per second, and ``speedup_vs_pk`` = pk time /
impl time. float64 rows add the non-torch peers of :mod:`benchmarks.peers` when installed (Pinocchio looped
from Python, Robotics Toolbox's C++ ``ETS.eval``; same Panda frames), timed on at most 10 000
configurations (their loops are linear in B). ``diffkin autograd`` is the default call with autograd
recording (the DH table requires grad). ``--compile`` adds ``chain.compile_fk()`` (torch.compile of a
per-entry kernel; the first call compiles, tens of seconds).
Memory rows (CPU, largest batch): peak extra resident memory of one call in a fresh process, and its ratio
to the output size (B·16 numbers).
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.common import FULL, QUICK, peak_rss_mb, pk_panda, print_table, sync, timeit
from diffkin import models

__all__ = ["run", "main"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: the Python/C++ loop peers are timed on at most this many configurations (rate per configuration)
PEER_MAX_BATCH = 10_000


def _bench(B: int, dtype: torch.dtype, device: str, min_time: float, repeats: int,
           compiled: bool, peers: bool = True) -> list[dict]:
    chain = models.load("panda", dtype=dtype, device=device)
    ref = pk_panda(dtype, device)
    q = chain.random_configuration((B,), generator=torch.Generator(device=device).manual_seed(0))
    impls = {"diffkin": lambda: chain.forward_kinematics(q)}
    if compiled:
        fast = models.load("panda", dtype=dtype, device=device).compile_fk()
        impls["diffkin compiled"] = lambda: fast.forward_kinematics(q)
    impls["pytorch_kinematics"] = lambda: ref.forward_kinematics(q).get_matrix()
    times = {}
    with torch.no_grad():
        for name, fn in impls.items():
            times[name] = timeit(fn, min_time, repeats, device)
        err = float((chain.forward_kinematics(q) - ref.forward_kinematics(q).get_matrix()).abs().max())
        T = chain.forward_kinematics(q)
    times["diffkin autograd"] = timeit(lambda: chain.forward_kinematics(q), min_time, repeats, device)
    sync(device)
    common = {"benchmark": "fk", "robot": "panda", "device": device, "dtype": str(dtype)[6:], "batch": B}
    rows = []
    for name, t in times.items():
        row = {**common, "impl": name, "seconds": t, "configs_per_s": B / t,
               "speedup_vs_pk": times["pytorch_kinematics"] / t}
        if name == "diffkin":
            row["max_abs_diff_vs_pk"] = err
        rows.append(row)
    if peers and dtype == torch.float64 and device == "cpu":
        rows += _peer_rows(q, T, times["pytorch_kinematics"], common, repeats)
    return rows


def _peer_rows(q: torch.Tensor, T: torch.Tensor, t_pk: float, common: dict, repeats: int) -> list[dict]:
    """float64 CPU peers from :mod:`benchmarks.peers` (skipped when not installed), timed on at most
    ``PEER_MAX_BATCH`` configurations (their loops scale linearly; the rate is per configuration)."""
    from benchmarks import peers

    B = q.shape[0]
    m = min(B, PEER_MAX_BATCH)
    q_np = q[:m].numpy()
    rows = []
    for name, fn in (("pinocchio (Python loop)", peers.pinocchio_fk_rate),
                     ("robotics_toolbox ETS.eval (C++)", peers.rtb_fk_rate)):
        try:
            rate, T_peer = fn(q_np, repeats=repeats)
        except peers.SkipPeer as e:
            print(f"[fk] {e}")
            continue
        t = B / rate
        err = float(abs(T_peer - T[:m].numpy()).max())
        rows.append({**common, "impl": name, "seconds": t, "configs_per_s": rate, "speedup_vs_pk": t_pk / t,
                     "max_abs_diff_vs_diffkin": err, "timed_batch": m})
    return rows


_MEM_CODE = """
import sys
sys.path.insert(0, ".")
from benchmarks.common import pk_panda
from diffkin import models
dtype = getattr(torch, "{dtype}")
B = {batch}
if "{impl}" == "diffkin":
    chain = models.load("panda", dtype=dtype)
    fk = lambda q: chain.forward_kinematics(q)
else:
    chain = pk_panda(dtype)
    fk = lambda q: chain.forward_kinematics(q).get_matrix()
with torch.no_grad():
    fk(torch.zeros(64, 7, dtype=dtype))
    q = torch.rand(B, 7, dtype=dtype)
    mark()
    T = fk(q)
"""


def _memory_rows(B: int, dtype_name: str) -> list[dict]:
    rows = []
    itemsize = torch.empty(0, dtype=_DTYPES[dtype_name]).element_size()
    out_mb = B * 16 * itemsize / 2**20
    for impl in ("diffkin", "pytorch_kinematics"):
        mb = peak_rss_mb(_MEM_CODE.format(dtype=dtype_name, batch=B, impl=impl))
        rows.append({"benchmark": "fk_memory", "impl": impl, "dtype": dtype_name, "batch": B,
                     "peak_extra_MiB": mb, "output_MiB": out_mb, "peak_over_output": mb / out_mb})
    return rows


def run(args=None) -> list[dict]:
    """FK rows for every (dtype, batch), plus memory rows at the largest CPU batch."""
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    batches = getattr(args, "batch", None) or ([1, 1000, 10000] if quick else [1, 1000, 100000])
    dtypes = getattr(args, "dtype", None) or ["float32", "float64"]
    device = getattr(args, "device", "cpu") or "cpu"
    threads = getattr(args, "threads", None) or 1
    min_time, repeats = QUICK if quick else FULL
    min_time = getattr(args, "min_time", None) or min_time
    repeats = getattr(args, "repeats", None) or repeats
    compiled = bool(getattr(args, "compile", False))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    rows = []
    try:
        for name in dtypes:
            for B in batches:
                rows += _bench(B, _DTYPES[name], device, min_time, repeats, compiled,
                               peers=not getattr(args, "no_peers", False))
    finally:
        torch.set_num_threads(old)
    for r in rows:
        r["threads"] = threads
    if device == "cpu" and not getattr(args, "no_memory", False):
        for name in dtypes:
            rows += _memory_rows(max(batches), name)
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, nargs="+", default=None, help="batch sizes (default 1 1000 100000)")
    p.add_argument("--dtype", nargs="+", choices=sorted(_DTYPES), default=None)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1: steadiest when busy)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--min-time", type=float, default=None)
    p.add_argument("--compile", action="store_true", help="also time chain.compile_fk() (slow first call)")
    p.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")
    p.add_argument("--no-peers", action="store_true", help="skip Pinocchio / Robotics Toolbox rows")
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    cols = ["dtype", "batch", "impl", "seconds", "configs_per_s", "speedup_vs_pk", "max_abs_diff_vs_pk",
            "max_abs_diff_vs_diffkin", "threads"]
    print_table([r for r in rows if r["benchmark"] == "fk"], "FK: Panda end-effector pose", cols)
    mem = [r for r in rows if r["benchmark"] == "fk_memory"]
    if mem:
        print_table(mem, "FK peak memory (one call)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
