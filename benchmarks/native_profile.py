"""Instructions, time and thread scaling of the fused C kernel per pose (issue 28, item 3), Panda, batch
100 000, float32 and float64, FK and FK + Jacobian.

    python -m benchmarks.native_profile [--batch 100000] [--reps 9] [--trials 7] [--no-callgrind]
                                        [--source OTHER.c] [--json out.json]

``--source`` profiles another version of ``_native.c`` of the same interface (``git show REV:path >
old.c``): the figures before and after a change of the kernel, in one run.

* ``instr/pose``: instructions of one ``dk_fk`` call counted by ``valgrind --tool=callgrind`` (repeatable on
  a shared machine, unlike time), divided by the batch. Valgrind cannot run AVX-512, so this is the AVX2
  build (``-march=x86-64-v3``: AVX2 + FMA, what an AVX2-only CPU gets from ``-march=native``).
* ``ns/pose``: the median (and the best) of ``--reps`` calls on one thread in
  :file:`benchmarks/native_driver.c` (no Python around the call), for the AVX2 build and for the build the
  library uses here (``-march=native``); ``cycles/pose`` multiplies the median by the clock of
  ``/proc/cpuinfo`` (``perf stat`` has no hardware counters on a virtual machine).
* ``flops/pose``: the arithmetic of the kernel's own formulas for this chain (multiply-adds counted as two,
  sin/cos by its polynomial), and ``flops/instr``: how much of each instruction is arithmetic (an AVX2 FMA
  of 4 doubles is 8 flops, of 8 floats 16).
* ``2 threads / 1``: the speed-up of ``native.fk_jacobian(threads=2)`` over ``threads=1`` through Python,
  the median (and best) of ``--trials`` interleaved pairs, and ``runnable``, the running / all tasks of
  ``/proc/loadavg`` after them: on a shared machine the second thread often finds its core taken, and the
  ratio then says more about the neighbours than about the kernel.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import re
import shutil
import statistics
import struct
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.common import print_table, write_json
from diffkin import models
from diffkin.kernels import native

__all__ = ["run", "main", "pose_flops", "dump_call", "AVX2"]

DRIVER = Path(__file__).with_name("native_driver.c")
AVX2 = ("-march=x86-64-v3", "-fopenmp")
_SINCOS = 36  # Cody-Waite reduction 8, sin polynomial 13, cos polynomial 15


def _panda(dtype):
    chain = models.load("panda", dtype=dtype)
    q = chain.random_configuration((1,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return chain, chain._native_model(q)


def _fixed_flops(A: list[float]) -> int:
    """P . A for a constant 3x4 A as the kernel does it (zeros skipped): per row, column c sums its
    non-zero a_kc (a multiply each, an add each but the first; the translation column adds to p)."""
    nz = [sum(A[4 * k + c] != 0 for k in range(3)) for c in range(4)]
    return 3 * sum(2 * z - (c < 3 and z > 0) for c, z in enumerate(nz))


def pose_flops(model: native.NativeModel, with_jacobian: bool) -> int:
    """Floating-point operations of one configuration in the kernel's formulas (see the module doc)."""
    ints, reals = model.ints, model.reals[torch.float64]
    J = len(ints["parent"])
    blocks = lambda name, i: reals[name][12 * i:12 * i + 12].tolist()  # noqa: E731
    prismatic = native._motion_codes["P"]  # the loaded library's code (the model was packed with it)
    rotating = [int(m) != prismatic for m in ints["motion"]]  # R (and S) motions rotate the frame
    flops = 0
    for j in range(J):
        flops += _fixed_flops(blocks("pre", j)) if ints["has_pre"][j] else 0
        flops += _fixed_flops(blocks("post", j)) if ints["has_post"][j] else 0
        flops += 2 + (_SINCOS + 18 if rotating[j] else 6)  # m q + b; the rotation of x, y or p += d z
    flops += sum(_fixed_flops(blocks("end", k)) for k in range(model.n_ends) if ints["has_end"][k])
    if with_jacobian:
        anc = ints["ancestor"].view(model.n_ends, J)
        flops += sum(24 if rotating[j] else 6 for k in range(model.n_ends) for j in range(J)
                     if anc[k, j])
    return flops


def dump_call(path: Path, model: native.NativeModel, q: torch.Tensor, with_jacobian: bool,
              threads: int = 1) -> None:
    """Write one ``dk_fk`` call (``threads`` threads) in the format of :file:`benchmarks/native_driver.c`."""
    B, K, n = q.shape[0], model.n_ends, model.n_vars
    out = {"q": q, "T": torch.zeros(B, K, 4, 4, dtype=q.dtype),
           "jac": torch.zeros(B, K, 6, n, dtype=q.dtype) if with_jacobian else None}
    tensors = {**model.ints, **model.reals[q.dtype], **{k: v for k, v in out.items() if v is not None}}
    args = model.call(q.dtype, batch=B, nthreads=threads, **out)
    pointers = [(getattr(native.Args, name).offset, t) for name, t in tensors.items()]
    with open(path, "wb") as f:
        f.write(struct.pack("<q", ctypes.sizeof(args)) + bytes(args) + struct.pack("<q", len(pointers)))
        for off, t in pointers:
            data = t.contiguous().numpy().tobytes()
            f.write(struct.pack("<qq", off, len(data)) + data)


def _driver(tmp: Path) -> Path:
    exe = tmp / "native_driver"
    cc = shutil.which("cc") or shutil.which("gcc")
    subprocess.run([cc, "-O2", "-o", str(exe), str(DRIVER), "-ldl"], check=True, capture_output=True)
    return exe


def _time_driver(exe: Path, lib: Path, dump: Path, reps: int) -> tuple[float, float]:
    """(best, median) seconds of ``reps`` calls."""
    out = subprocess.run([str(exe), str(lib), str(dump), str(reps)], check=True, capture_output=True,
                         text=True).stdout
    return float(re.search(r"best (\S+)", out).group(1)), float(re.search(r"median (\S+)", out).group(1))


def _callgrind(exe: Path, lib: Path, dump: Path, tmp: Path) -> int | None:
    if shutil.which("valgrind") is None:
        return None
    cg = tmp / "callgrind.out"
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}", "--collect-atstart=no",
                    "--toggle-collect=dk_fk", str(exe), str(lib), str(dump), "1"], check=True,
                   capture_output=True)
    return int(re.search(r"^summary:\s+(\d+)", cg.read_text(), re.M).group(1))


def _clock_ghz() -> float | None:
    try:
        mhz = re.findall(r"cpu MHz\s*:\s*([\d.]+)", Path("/proc/cpuinfo").read_text())
        return float(mhz[0]) / 1000 if mhz else None
    except OSError:
        return None


def _thread_ratio(model, q, with_jacobian: bool, trials: int) -> dict:
    """Over ``trials`` interleaved 1- / 2-thread pairs: the median rate at 1 thread, and the median and best
    wall-clock ratio t(1) / t(2); the runnable tasks of ``/proc/loadavg`` at the end say how busy it was."""
    one, wall = [], []
    for _ in range(trials):
        ts = []
        for threads in (1, 2):
            native.fk_jacobian(model, q, with_jacobian, threads=threads)  # warm
            t0 = time.perf_counter()
            native.fk_jacobian(model, q, with_jacobian, threads=threads)
            ts.append(time.perf_counter() - t0)
        one.append(ts[0])
        wall.append(ts[0] / ts[1])
    try:
        runnable = Path("/proc/loadavg").read_text().split()[3]
    except OSError:
        runnable = None
    return {"M/s 1 thread": q.shape[0] / statistics.median(one) / 1e6,
            "2 threads / 1": statistics.median(wall), "2 threads / 1 (best)": max(wall), "runnable": runnable}


def run(args) -> list[dict]:
    B, reps = getattr(args, "batch", 100_000), getattr(args, "reps", 9)
    trials, use_cg = getattr(args, "trials", 7), getattr(args, "callgrind", True)
    if not native.available():
        raise SystemExit("the native kernel is not built here")
    source = getattr(args, "source", None)
    with contextlib.ExitStack() as stack:
        if source:  # the other source's libraries (cached under their own hash), its kernel for the threads
            stack.enter_context(_patched(native, "_SOURCE", Path(source).resolve()))
            flags = native._OPTIONAL[0]
            stack.enter_context(_patched(native, "_lib", native._load(native._compile(flags), flags)))
        libs = {"native": native._compile(native._OPTIONAL[0]), "avx2": native._compile(AVX2)}
        return _rows(libs, B, reps, trials, use_cg)


@contextlib.contextmanager
def _patched(obj, name: str, value):
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


def _rows(libs: dict, B: int, reps: int, trials: int, use_cg: bool) -> list[dict]:
    ghz, rows = _clock_ghz(), []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        exe = _driver(tmp)
        for dtype in (torch.float32, torch.float64):
            chain, model = _panda(dtype)
            q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(1))
            for jac in (False, True):
                dump = tmp / "call.bin"
                dump_call(dump, model, q, jac)
                flops = pose_flops(model, jac)
                instr = _callgrind(exe, libs["avx2"], dump, tmp) if use_cg else None
                row = {"call": "FK + J" if jac else "FK",
                       "dtype": str(dtype).removeprefix("torch."), "batch": B, "flops/pose": flops,
                       "instr/pose (AVX2)": instr / B if instr else None,
                       "flops/instr": flops * B / instr if instr else None}
                for name, lib in libs.items():
                    best, median = (t / B * 1e9 for t in _time_driver(exe, lib, dump, reps))
                    row[f"ns/pose ({name})"] = median
                    row[f"best ns/pose ({name})"] = best
                    if ghz:
                        row[f"cycles/pose ({name})"] = median * ghz
                row.update(_thread_ratio(model, q, jac, trials))
                rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=100_000)
    p.add_argument("--reps", type=int, default=9, help="driver calls per figure (median)")
    p.add_argument("--trials", type=int, default=7, help="interleaved 1- / 2-thread pairs (median)")
    p.add_argument("--no-callgrind", dest="callgrind", action="store_false")
    p.add_argument("--source", default=None, help="profile this _native.c instead (same interface)")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    rows = run(args)
    print_table(rows, "native kernel per pose")
    if args.json:
        write_json(args.json, rows, {"clock_ghz": _clock_ghz(), "libraries": "native, avx2"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
