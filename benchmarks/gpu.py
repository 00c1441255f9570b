"""FK, Jacobian and ``ik.solve`` of the Panda at batch 10⁶ on CUDA, printed as one table (issue 28, item 4).

    python -m benchmarks.gpu [--device cuda|cpu] [--batch 1000000] [--ik-batch N] [--dtype float32]
                             [--compile | --no-compile] [--no-graphs] [--quick] [--json out.json]

Rows, per workload (``fk``: ``chain.forward_kinematics``; ``jacobian``:
``chain.forward_kinematics_and_jacobian``, pose and geometric Jacobian (3.30); ``ik.solve``: full-pose
targets reached by FK of random configurations, 0.1 mm / 1 mrad):

* ``eager``: the call as a user makes it, under ``torch.no_grad()`` (on the CPU: the fused C kernel);
* ``cuda graph`` (CUDA only): the call captured once into a ``torch.cuda.CUDAGraph`` on static input and
  output buffers, then replayed: one launch instead of one per operator, which is what a batch-10⁶ call of a
  few hundred small kernels gains most from;
* ``torch.compile``: ``torch.compile(fullgraph=True)`` of the same call (fused elementwise kernels; the first
  call compiles, tens of seconds, not timed). On by default on CUDA, opt-in (``--compile``) on the CPU;
* ``ik.solve``: eager only (its scheduling between rounds reads a few counts back to the host, which a graph
  cannot hold), with the success rate.

``seconds`` is the median of timed blocks (:func:`benchmarks.common.timeit`, CUDA synchronised),
``per_s`` configurations (or targets) per second, ``speedup_vs_eager`` the ratio in the same run and
``max_abs_diff_vs_eager`` the largest difference of the outputs from the eager call's.

``--device cpu`` (with a small ``--batch``) runs every row but the graphs on the CPU, so the script is tested
in CI (``tests/test_bench_gpu.py``) and cannot rot. Measured once on a lent NVIDIA H200 (torch 2.11, CUDA 13):
``docs/bench/gpu_h200.txt`` (FK 1.3·10⁹ poses/s eager, 1.5·10⁹ in a CUDA graph; ``ik.solve`` 1.4·10⁶
targets/s at 100 % success; ``torch.compile`` slower than eager there, 0.39–0.51×).
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.common import FULL, QUICK, print_table, sync, timeit, write_json
from diffkin import ik, models

__all__ = ["run", "main", "parse_args"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _graphed(fn, x: torch.Tensor):
    """``fn`` captured into a CUDA graph on a static copy of ``x``: returns ``replay() -> outputs``."""
    static_x = x.clone()
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):  # warm-up off the capture (allocator, lazy init), as the docs ask
        for _ in range(3):
            fn(static_x)
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        static_out = fn(static_x)

    def replay():
        graph.replay()
        return static_out

    return replay


def _compiled(fn, x: torch.Tensor):
    """``fn`` through ``torch.compile(fullgraph=True)``: ``call() -> fn(x)``, compiled on the first call."""
    fast = torch.compile(fn, fullgraph=True)
    return lambda: fast(x)


def _max_diff(a, b) -> float:
    a, b = (a,) if torch.is_tensor(a) else a, (b,) if torch.is_tensor(b) else b
    return max(float((x - y).abs().max()) for x, y in zip(a, b))


def _kernel_rows(name: str, fn, q: torch.Tensor, device: str, timing, graphs: bool, compiled: bool):
    """Rows of one workload ``fn(q)``: eager, and where asked the CUDA graph and torch.compile forms."""
    ref = fn(q)
    t_eager = timeit(lambda: fn(q), *timing, device=device)
    rows = [{"workload": name, "impl": "eager", "seconds": t_eager}]
    variants = []
    if graphs and device.startswith("cuda"):
        variants.append(("cuda graph", lambda: _graphed(fn, q)))
    if compiled:
        variants.append(("torch.compile", lambda: _compiled(fn, q)))
    for impl, make in variants:
        try:
            call = make()
            out = call()  # the compile (or a replay) before timing
            sync(device)
        except Exception as e:  # a form that does not work here is a finding, not a crash
            rows.append({"workload": name, "impl": impl, "note": f"failed: {type(e).__name__}: {e}"[:120]})
            continue
        t = timeit(call, *timing, device=device)
        rows.append({"workload": name, "impl": impl, "seconds": t, "speedup_vs_eager": t_eager / t,
                     "max_abs_diff_vs_eager": _max_diff(out, ref)})
    return rows


def _ik_rows(chain, n: int, device: str, repeats: int) -> list[dict]:
    gen = torch.Generator(device=device).manual_seed(1)
    with torch.no_grad():
        T = chain.forward_kinematics(chain.random_configuration((n,), generator=gen))
    res = [None]

    def solve():
        res[0] = ik.solve(chain, T, seed=0)

    t = timeit(solve, 0.0, repeats, device=device, warmup=1)
    return [{"workload": "ik.solve", "impl": "eager", "batch": n, "seconds": t, "per_s": n / t,
             "success": float(res[0].success.float().mean())}]


def run(args) -> list[dict]:
    device = getattr(args, "device", "cuda") or "cuda"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("no CUDA device here: run with --device cpu (and a small --batch)")
    quick = getattr(args, "quick", False)
    B = getattr(args, "batch", None) or 1_000_000
    n_ik = getattr(args, "ik_batch", None) or B
    dtype = _DTYPES[getattr(args, "dtype", None) or "float32"]
    compiled = getattr(args, "compile", None)
    compiled = device.startswith("cuda") if compiled is None else compiled
    graphs = not getattr(args, "no_graphs", False)
    timing = QUICK if quick else FULL
    chain = models.load("panda", dtype=dtype, device=device)
    q = chain.random_configuration((B,), generator=torch.Generator(device=device).manual_seed(0))
    rows = []
    with torch.no_grad():
        for name, fn in (("fk", lambda x: chain.forward_kinematics(x, check=False)),
                         ("jacobian", lambda x: chain.forward_kinematics_and_jacobian(x, check=False))):
            rows += [{**r, "batch": B} for r in _kernel_rows(name, fn, q, device, timing, graphs, compiled)]
    rows += _ik_rows(chain, n_ik, device, timing[1])
    for r in rows:
        if "seconds" in r and "per_s" not in r:
            r["per_s"] = r["batch"] / r["seconds"]
        r.update(benchmark="gpu", device=device, dtype=str(dtype).removeprefix("torch."))
    return rows


_COLUMNS = ["workload", "impl", "device", "dtype", "batch", "seconds", "per_s", "speedup_vs_eager",
            "max_abs_diff_vs_eager", "success", "note"]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    p.add_argument("--batch", type=int, default=None, help="FK / Jacobian batch (default 1 000 000)")
    p.add_argument("--ik-batch", type=int, default=None, help="ik.solve targets (default: --batch)")
    p.add_argument("--dtype", choices=sorted(_DTYPES), default="float32")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--compile", dest="compile", action="store_true", default=None,
                   help="add torch.compile rows (default on CUDA)")
    g.add_argument("--no-compile", dest="compile", action="store_false")
    p.add_argument("--no-graphs", action="store_true", help="skip the CUDA graph rows")
    p.add_argument("--quick", action="store_true", help="short timing blocks")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = run(args)
    print_table(rows, f"FK, Jacobian and ik.solve of the Panda on {args.device}", _COLUMNS)
    if args.json:
        write_json(args.json, rows, {"benchmark": "gpu"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
