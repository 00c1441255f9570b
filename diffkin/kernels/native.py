"""The fused native kernel: the chain product (2.50) and the geometric Jacobian (3.30) in one C pass.

``_native.c`` is a second implementation of exactly what :func:`diffkin.kernels.tree.column_frames` and
:mod:`diffkin.kernels.jacobian` compute, for the case where they are slowest: CPU tensors without autograd.
It reads the same constants (the chain's fixed transforms as float plans: the
:class:`~diffkin.kernels.tree.Segments` of ``per_joint=True``), works on blocks of 16 configurations with
vectorised loops, and shares the blocks between threads with a dynamic schedule. ``tests/test_native.py``
checks it against the torch kernels (every joint kind, trees, mimic joints, base and tool, both dtypes).

Build: the C file is compiled on first use (about 1 s) with the system's C compiler (``$CC``, else ``cc``)
into ``$DIFFKIN_CACHE_DIR`` (default ``$XDG_CACHE_HOME/diffkin`` or ``~/.cache/diffkin``), once per source,
flags and CPU; ``python -m diffkin.kernels`` builds it ahead of time (``make`` does) and prints
where. Without a compiler, or with ``DIFFKIN_NATIVE=0`` in the environment, :func:`available` is False and
every caller keeps the torch kernels: results are the same to rounding.

Thread policy: batches of at most 512 configurations run on the calling thread. Larger ones use
``torch.get_num_threads()`` threads, but never more than the cores that are free right now: the count of
runnable tasks in ``/proc/loadavg`` (read at most every 0.1 s) minus this call's own thread is taken off
the cores this process may run on. A fork-join call waits for its slowest thread, and a thread that shares
a core with a busy process is preempted for whole scheduler slices (milliseconds): on a 2-core machine with
one core busy, two threads made FK 10× slower than one. With the policy a busy core costs at most its
share (≤ 2× on 2 cores). Blocks are also handed out dynamically, for cores that are slower for other
reasons. ``threads=`` on :func:`fk_jacobian` overrides the policy.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import torch
from torch import Tensor

from .tree import Segments, Topology

__all__ = ["available", "build", "disabled", "library_path", "free_cores", "thread_count", "NativeModel",
           "native_model", "fk_jacobian", "LMProblem", "lm_steps", "status", "NativeBuildWarning"]

_SOURCE = Path(__file__).with_name("_native.c")
_FLAGS = ("-O3", "-fPIC", "-shared", "-fno-math-errno")
_OPTIONAL = (("-march=native", "-fopenmp"), ("-fopenmp",), ("-fopenmp-simd",), ())  # tried in this order
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_tried = False
_error: str | None = None
_disabled = 0  # depth of `disabled()` contexts
_path: Path | None = None  # the loaded library
_announced = False


class NativeBuildWarning(UserWarning):
    """Said once per process: the fused kernel is being compiled (where to), or could not be (why)."""


def _announce(text: str) -> None:
    global _announced
    if not _announced:
        _announced = True
        warnings.warn(f"diffkin: {text}", NativeBuildWarning, stacklevel=2)


def _cache_dir() -> Path:
    env = os.environ.get("DIFFKIN_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "diffkin"


def _cpu_signature() -> str:
    """What -march=native depends on: the CPU model and flags (a cache shared between machines of
    different CPUs must not hand one the other's instructions)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        lines = [ln for ln in text.splitlines() if ln.startswith(("flags", "model name", "Features"))]
        return "\n".join(sorted(set(lines)))
    except OSError:
        return platform.processor() or platform.machine()


def library_path(flags: tuple[str, ...] = ()) -> Path:
    """Where the library for this source, ``flags`` and CPU is cached."""
    h = hashlib.sha256()
    for part in (_SOURCE.read_bytes(), " ".join(_FLAGS + flags).encode(), _cpu_signature().encode(),
                 platform.machine().encode(), sys.platform.encode()):
        h.update(part)
    return _cache_dir() / f"diffkin_native-{h.hexdigest()[:16]}.so"


def _compile(flags: tuple[str, ...]) -> Path:
    out = library_path(flags)
    if out.exists():
        return out
    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise RuntimeError("no C compiler found (set CC)")
    _announce(f"compiling the fused C kernel once (a few seconds) into {out.parent}; "
              "`python -m diffkin.kernels` does it ahead of time, DIFFKIN_NATIVE=0 keeps the torch kernels")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        cmd = [cc, *_FLAGS, *flags, "-o", tmp, str(_SOURCE), "-lm"]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {res.stderr.strip()[-500:]}")
        os.replace(tmp, out)  # atomic: concurrent builders (test workers, ranks) never see half a file
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def build() -> Path:
    """Compile (or find in the cache) and load the library; returns its path. Raises ``RuntimeError``
    with the compiler's message when no flag set compiles."""
    global _lib, _tried, _error, _path
    with _lock:
        errors = []
        for flags in _OPTIONAL:
            try:
                path = _compile(flags)
                lib = ctypes.CDLL(str(path))
            except (RuntimeError, OSError, subprocess.SubprocessError) as e:
                errors.append(str(e))
                continue
            ptr, i64, cint = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
            for suffix, real in (("f64", ctypes.c_double), ("f32", ctypes.c_float)):
                fn = getattr(lib, f"dk_fk_{suffix}")
                fn.restype = i64
                fn.argtypes = [ptr, ptr, ptr, i64, ptr, ptr, cint]
                fn = getattr(lib, f"dk_lm_{suffix}")
                fn.restype = i64
                fn.argtypes = [ptr, ptr, i64, cint, cint, ptr, ptr, ptr, i64, ptr, ptr, ptr, ptr, ptr, ptr,
                               ptr, ptr, real, real, real, real, real, ptr, ptr, ptr, cint]
            _lib, _tried, _error, _path = lib, True, None, path
            return path
        _tried, _error = True, "; ".join(dict.fromkeys(errors))  # each reason once
        raise RuntimeError(f"the native kernel could not be built: {_error}")


def available() -> bool:
    """True when the native kernel is built and loaded (built on the first call; False without a C
    compiler or with ``DIFFKIN_NATIVE=0``)."""
    if _disabled:
        return False
    if _lib is not None:
        return True
    if _tried or os.environ.get("DIFFKIN_NATIVE", "1") == "0":
        return False
    try:
        build()
    except RuntimeError:
        _announce(f"the fused C kernel is not in use ({_error}); the torch kernels serve every call (the "
                  "same results, slower on CPU without autograd)")
        return False
    return True


def status() -> tuple[bool, str]:
    """``(in use, what)``: the library's path, or why the torch kernels serve every call
    (``DIFFKIN_NATIVE=0``, no C compiler, the compiler's error). Builds it if not tried yet (silently)."""
    if os.environ.get("DIFFKIN_NATIVE", "1") == "0":
        return False, "disabled by DIFFKIN_NATIVE=0"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NativeBuildWarning)
        ok = available()
    if ok:
        return True, str(_path)
    if _disabled:
        return False, "disabled (inside native.disabled())"
    err = _error or "not built"
    if "no C compiler" in err:
        return False, "no C compiler found (set CC); the torch kernels serve every call"
    return False, f"build failed ({err}); the torch kernels serve every call"


_SERIAL_MAX = 512  # as SERIAL_MAX in _native.c: smaller batches never start a thread
_free = [0.0, 0]  # (time of the reading, free cores)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def free_cores() -> int:
    """Cores of this process's affinity set not running another task right now (at least 1): the
    instantaneous runnable count of ``/proc/loadavg`` less the reader itself, remembered for 0.1 s. Without
    ``/proc`` (not Linux): every core."""
    now = time.monotonic()
    if now - _free[0] < 0.1:
        return _free[1]
    cores = _cores()
    try:
        with open("/proc/loadavg") as f:
            running = int(f.read().split()[3].split("/")[0])
        free = max(1, cores - max(running - 1, 0))
    except (OSError, ValueError, IndexError):
        free = cores
    _free[0], _free[1] = now, free
    return free


def thread_count(batch: int, requested: int | None = None) -> int:
    """Threads the kernel uses for ``batch`` configurations: 1 up to 512, else ``requested`` (default
    ``torch.get_num_threads()``) capped by :func:`free_cores` (see the module doc)."""
    if batch <= _SERIAL_MAX:
        return 1
    requested = torch.get_num_threads() if requested is None else requested
    return 1 if requested <= 1 else min(requested, free_cores())


@contextlib.contextmanager
def disabled():
    """Within the block every caller uses the torch kernels (for comparisons and tests; not thread-local)."""
    global _disabled
    _disabled += 1
    try:
        yield
    finally:
        _disabled -= 1


class NativeModel:
    """A chain's constants packed for the C kernel: int32 structure and float64 / float32 reals."""

    __slots__ = ("ints", "reals", "n_ends", "n_vars")

    def __init__(self, topo: Topology, seg: Segments):
        J, K = topo.n_frames, len(topo.ends)

        def rows(plan) -> list[float]:  # a Plan (R, t) -> 3x4 row-major; None: identity
            if plan is None:
                return [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
            R, t = plan
            return [v for r in range(3) for v in (*R[r], t[r])]

        pre = list(seg.pre) if seg.pre is not None else [None] * J
        post = list(seg.post) if seg.post is not None else [None] * J
        off = list(seg.offset) if seg.offset is not None else [0.0] * J
        for T in (*pre, *post, seg.base, *seg.ends):
            if T is not None and not isinstance(T, tuple):
                raise TypeError("NativeModel needs constant plans (Segments from per_joint=True constants)")
        ints = [J, K, topo.n_vars, *topo.parents, *map(int, topo.revolute), *topo.q_index,
                *(int(p is not None) for p in pre), *(int(p is not None) for p in post),
                int(seg.base is not None), *topo.ends, *(int(E is not None) for E in seg.ends),
                *(int(a) for row in topo.ancestors for a in row)]
        reals = [*topo.multiplier, *(b + float(o or 0.0) for b, o in zip(topo.q_offset, off))]
        for plans in (pre, post):
            for p in plans:
                reals += rows(p)
        reals += rows(seg.base)
        for E in seg.ends:
            reals += rows(E)
        self.ints = torch.tensor(ints, dtype=torch.int32)
        r64 = torch.tensor(reals, dtype=torch.float64)
        self.reals = {torch.float64: r64, torch.float32: r64.to(torch.float32)}
        self.n_ends, self.n_vars = K, topo.n_vars


def native_model(topo: Topology, seg: Segments) -> NativeModel:
    """The packed constants of ``seg``, made once per Segments object (kept on it)."""
    packed = seg.__dict__.get("_native")
    if packed is None:
        packed = NativeModel(topo, seg)
        object.__setattr__(seg, "_native", packed)  # Segments is frozen; the pack is derived data
    return packed


def fk_jacobian(model: NativeModel, q: Tensor, with_jacobian: bool = False,
                threads: int | None = None) -> tuple[Tensor, Tensor | None, int]:
    """``q (B, n)`` (CPU, float32/float64, contiguous) -> ``(T (B, K, 4, 4), J (B, K, 6, n) or None,
    non-finite count)``: the end-link poses (2.50) and geometric Jacobians (3.30). Rows whose q holds
    NaN/inf are not meaningful; the caller raises on a non-zero count. ``threads``: a fixed count instead of
    the policy of :func:`thread_count`."""
    B, n, K = q.shape[0], model.n_vars, model.n_ends
    T = torch.empty(B, K, 4, 4, dtype=q.dtype)
    J = torch.empty(B, K, 6, n, dtype=q.dtype) if with_jacobian else None
    fn = _lib.dk_fk_f64 if q.dtype == torch.float64 else _lib.dk_fk_f32
    bad = fn(model.ints.data_ptr(), model.reals[q.dtype].data_ptr(), q.data_ptr(), B, T.data_ptr(),
             None if J is None else J.data_ptr(), threads or thread_count(B))
    if bad < 0:
        raise MemoryError("the native kernel could not allocate its per-thread frames")
    return T, J, bad


class LMProblem:
    """The fixed inputs of :func:`lm_steps` for one solve, converted once: the packed chain, the targets
    ``pd (3K, N)`` and rotation columns ``(x, y, z)`` (each ``(3K, N)``, or None: position only), the row
    weights ``sqrt_w`` and the joint map q = c + h sin(u) on ``bounded`` joints (``(n,)`` each), in the
    working dtype."""

    def __init__(self, model: NativeModel, pd: Tensor, cols, sqrt_w: Tensor, c: Tensor, h: Tensor,
                 bounded: Tensor):
        dtype = pd.dtype
        self.model, self.dtype, self.N = model, dtype, pd.shape[1]
        self.targets = [pd.contiguous(), *((None,) * 3 if cols is None else (t.contiguous() for t in cols))]
        self.vectors = [t.reshape(-1).to(dtype).contiguous() for t in (sqrt_w, c, h)]
        self.bounded = bounded.reshape(-1).to(torch.uint8).contiguous()
        self.fn = _lib.dk_lm_f64 if dtype == torch.float64 else _lib.dk_lm_f32
        self.pointers = (*(None if t is None else t.data_ptr() for t in self.targets),
                         *(t.data_ptr() for t in self.vectors), self.bounded.data_ptr())


def lm_steps(problem: LMProblem, u: Tensor, tidx: Tensor, *, damping2: float, error_damping: float,
             tolerances: tuple[float, float], margin: float, iterations: int, max_rounds: int = 1,
             threads: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, int, Tensor]:
    """Rounds of ``iterations`` steps of :func:`diffkin.ik.solve`'s Levenberg–Marquardt iteration on m rows,
    batch last.

    ``u (n, m)``: the solver's variables of rows aiming at targets ``tidx (m,)`` of ``problem``. Per step:
    the pose error (3.78) and rotation-vector error (the ``"rotvec"`` form of
    :func:`~diffkin.kernels.pose_error.orientation_error`), λ = damping2 + error_damping ‖e_w‖², the damped
    least-squares step (3.59) on the weighted Jacobian, applied where not converged (max ‖e_p‖ ≤ tol_p ·
    margin and max θ ≤ tol_o · margin). Up to ``max_rounds`` rounds run back to back, stopping after one in
    which a row converged (the caller may only ask for rounds after which its schedule would do nothing).

    Returns ``(u after the steps, u of the last evaluation, converged (m,) bool, merit (m,), rounds run,
    merit of the round before the last (m,))`` with merit = max(‖e_p‖ / tol_p, θ / tol_o), the first four as
    :meth:`diffkin.ik._lm._Run.steps` returns them.
    """
    m = u.shape[1]
    u_new = u.clone(memory_format=torch.contiguous_format)
    u_eval = torch.empty_like(u_new)
    conv = torch.empty(m, dtype=torch.bool)
    merit, merit_prev = torch.empty(2, m, dtype=problem.dtype).unbind(0)
    tidx = tidx.contiguous()
    tp, to = tolerances
    rounds = problem.fn(problem.model.ints.data_ptr(), problem.model.reals[problem.dtype].data_ptr(), m,
                        iterations, max_rounds, u_new.data_ptr(), u_eval.data_ptr(), tidx.data_ptr(),
                        problem.N, *problem.pointers, damping2, error_damping, tp, to, margin,
                        conv.data_ptr(), merit.data_ptr(), merit_prev.data_ptr(), threads or thread_count(m))
    if rounds < 0:
        raise MemoryError("the native kernel could not allocate its per-thread work space")
    return u_new, u_eval, conv, merit, rounds, merit_prev


def _main() -> int:
    if os.environ.get("DIFFKIN_NATIVE", "1") == "0":
        print("diffkin native kernel: disabled (DIFFKIN_NATIVE=0)")
        return 0
    try:
        with warnings.catch_warnings():  # this command says it itself
            warnings.simplefilter("ignore", NativeBuildWarning)
            path = build()
    except RuntimeError as e:  # not an install failure: the torch kernels serve every call
        print(f"diffkin native kernel: not built, the torch kernels will be used ({e})")
        return 0
    print(f"diffkin native kernel: {path}")
    return 0

