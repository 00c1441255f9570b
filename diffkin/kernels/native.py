"""The fused native kernel: the chain product (2.50) and the geometric Jacobian (3.30) in one C pass.

``_native.c`` is a second implementation of exactly what :func:`diffkin.kernels.tree.column_frames` and
:mod:`diffkin.kernels.jacobian` compute, for the case where they are slowest: CPU tensors without autograd.
It reads the same constants (the chain's fixed transforms as float plans: the
:class:`~diffkin.kernels.tree.Segments` of ``per_joint=True``), works on blocks of 16 configurations with
vectorised loops, and shares the blocks between threads with a dynamic schedule. ``tests/test_native.py``
checks it against the torch kernels (every joint kind, trees, mimic joints, base and tool, both dtypes),
``tests/test_native_ball.py`` ball and free joints against the torch kernels and MuJoCo.

Motions: each frame carries the code of its elementary motion (R, P or S of
:mod:`diffkin.kernels.configuration`). The C file's table of motions (``DK_MOTIONS``: letter, nq, nv, in
code order) is read at load time through ``dk_motions`` and must equal ``MOTION_NQ`` / ``MOTION_NV``; the
packer gives each frame the code of its letter in that table, so one table drives both kernels.

Build: the C file is compiled on first use (about 1 s) with the system's C compiler (``$CC``, else ``cc``)
into ``$DIFFKIN_CACHE_DIR`` (default ``$XDG_CACHE_HOME/diffkin`` or ``~/.cache/diffkin``), once per source,
flags and CPU; ``python -m diffkin.kernels`` builds it ahead of time (``make`` does) and prints
where. Without a compiler, or with ``DIFFKIN_NATIVE=0`` in the environment, :func:`available` is False and
every caller keeps the torch kernels: results are the same to rounding.

Interface: one struct per entry point, each mirrored field by field by a ``ctypes.Structure`` here:
:class:`Args` (``dk_args``: the chain's arrays and one FK call, for ``dk_fk`` and as the chain of every
other entry), :class:`SolveArgs` (``dk_solve_args``: the chain's address, the LM constants and one solve,
for ``dk_solve`` and ``dk_solve_one``), :class:`WatchArgs` (``dk_watch``: the cache check of the lean
paths) and :class:`Collide` (``dk_collide``); ``ik/_native_velocity.py``'s ``Vel`` (``dk_vel``) follows
the same rule. Each starts with its own version (the class's ``VERSION``) and its size, so that a new
solver option changes :class:`SolveArgs` and its version only, never the FK's :class:`Args`. On loading,
:func:`check_abi` reads every struct's version, ``sizeof``, field names and offsets from the library
(``dk_layout_<tag>`` / ``dk_names_<tag>``, one generic check: :func:`check_layout`), the status codes and
limits Python uses (``dk_constants``, checked against :data:`CONSTANTS`: :func:`check_constants`) and the
table of motions; a library that does not match is rebuilt once, then refused: a one-time warning, and the
torch kernels serve every call. Every entry point refuses, at call time, a struct of another version or
size (``DK_ABI_ERROR``: :class:`AbiMismatch` here).

Thread policy: batches of at most 512 configurations run on the calling thread. Larger ones use
``torch.get_num_threads()`` threads, but never more than the cores that are free right now: the count of
runnable tasks in ``/proc/loadavg`` (read at most every 0.1 s) minus this process's own runnable threads
is taken off the cores this process may run on. A fork-join call waits for its slowest thread, and a
thread that shares a core with a busy process is preempted for whole scheduler slices (milliseconds): on a
2-core machine with one core busy, two threads made FK 10× slower than one. With the policy a busy core
costs at most its share (≤ 2× on 2 cores). Blocks are also handed out dynamically, for cores that are
slower for other reasons. ``threads=`` on :func:`fk_jacobian` overrides the policy. Within
``with native.threads(n):`` (:func:`threads`) every kernel called from this thread asks for ``n`` threads
instead of torch's count, for batches of any size (the 512 floor is off), still capped by the free
cores: the C kernels' threads then do not follow torch's (whose extra threads slow the small torch ops
between the kernels down on a loaded machine).
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

from ..errors import OptionError
from .configuration import MOTION_NQ, MOTION_NV
from .tree import Segments, Topology

__all__ = ["available", "build", "disabled", "library_path", "free_cores", "thread_count", "threads",
           "NativeModel", "Collide", "capsules_clear", "collide_struct",
           "fk_jacobian", "status", "NativeBuildWarning", "Args", "SolveArgs", "WatchArgs",
           "ABI_VERSION", "CONSTANTS", "STRUCTS", "AbiMismatch", "solve_call", "new_struct", "contiguous_as",
           "check_abi",
           "check_layout", "check_constants", "banded_solve", "ClipArgs", "clip_rows", "clip_joint",
           "clip_step", "jacobian_support", "topp_grid", "topp_peaks", "topp_sample", "spline_fine",
           "spline_marks"]

_SOURCE = Path(__file__).with_name("_native.c")
_INCLUDED = (Path(__file__).with_name("_native_solve.c"),  # #included by _native.c: part of its source
             Path(__file__).with_name("_native_collide.c"),
             Path(__file__).with_name("_native_plan.c"),
             Path(__file__).with_name("_native_velocity.c"),
             Path(__file__).with_name("_native_banded.c"),
             Path(__file__).with_name("_native_clip.c"),
             Path(__file__).with_name("_native_topp.c"),
             Path(__file__).with_name("_native_spline.c"))
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


#: the version of ``dk_args`` this module speaks (DK_ABI_VERSION in _native.c)
ABI_VERSION = 4
#: the status codes and limits of the library that Python uses (DK_CONSTANTS in _native.c), checked equal to
#: the library's at load (:func:`check_constants`); the other modules read them from here
CONSTANTS = {"DK_ABI_ERROR": -2, "DK_RANGE_ERROR": -3, "DK_STALE": -4, "DK_NOT_RIGID": -5, "SERIAL_MAX": 512,
             "MAX_RANKS": 64, "MAX_ENDS": 64, "COVER_SLACK": 3}
_ABI_ERROR, _RANGE_ERROR = CONSTANTS["DK_ABI_ERROR"], CONSTANTS["DK_RANGE_ERROR"]
_motion_codes: dict[str, int] = {}  # letter -> code, from the loaded library's DK_MOTIONS
_I64, _F64, _PTR = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
_HEAD = [("version", _I64), ("size", _I64)]  # every struct's first fields


class Args(ctypes.Structure):
    """``dk_args`` of ``_native.c`` (``DK_ARGS_FIELDS``, where each field is described), field by field:
    the version and the size, the chain's arrays, one FK call's inputs and outputs."""

    VERSION = ABI_VERSION
    _fields_ = _HEAD + \
        [(name, _I64) for name in ("real_bytes", "nthreads", "J", "K", "n", "nv", "has_base")] + \
        [(name, _PTR) for name in ("parent", "motion", "qidx", "vidx", "has_pre", "has_post", "end_joint",
                                   "has_end", "ancestor", "mult", "qoff", "pre", "post", "base", "end")] + \
        [("batch", _I64), ("q", _PTR), ("T", _PTR), ("jac", _PTR)]


class SolveArgs(ctypes.Structure):
    """``dk_solve_args`` of ``_native_solve.c`` (``DK_SOLVE_FIELDS``): the arguments of ``dk_solve`` and
    ``dk_solve_one``: the address of the chain's :class:`Args` (``chain``), the LM constants, the targets,
    the seeds and the outputs. A new solver option is a field here and a new :attr:`VERSION` (with
    ``DK_SOLVE_VERSION``)."""

    VERSION = 1
    _fields_ = _HEAD + [("nthreads", _I64), ("chain", _PTR), ("iters", _I64), ("n_targets", _I64)] + \
        [(name, _PTR) for name in ("pd", "xd", "yd", "zd", "sqrt_w", "jc", "jh", "bounded")] + \
        [(name, _F64) for name in ("damping2", "error_damping", "tol_p", "tol_o", "margin")] + \
        [(name, _I64) for name in ("n_seeds", "max_iterations", "min_seed_iterations")] + \
        [("stall_ratio", _F64), ("n_user", _I64), ("user_u", _PTR), ("n_lib", _I64), ("lib_ranks", _I64),
         ("lib_u", _PTR), ("lib_pose", _PTR), ("feature_weight", _F64), ("n_pool", _I64)] + \
        [(name, _PTR) for name in ("pool", "qlo", "qhi", "wrap")] + [("clamp", _I64)] + \
        [(name, _PTR) for name in ("q_out", "iters_out", "seeds_out", "pos_err", "ori_err", "success")] + \
        [("target_stride", _I64)]


class WatchArgs(ctypes.Structure):
    """``dk_watch`` of ``_native.c`` (``DK_WATCH_FIELDS``): the byte snapshot the lean paths' entry points
    compare before they compute (:class:`diffkin.kernels.cache.Watch`)."""

    VERSION = 1
    _fields_ = _HEAD + [("n", _I64), ("ptr", _PTR), ("bytes", _PTR), ("snap", _PTR), ("work", _PTR),
                        ("ready", _I64), ("busy", _I64)]


class Collide(ctypes.Structure):
    """``dk_collide`` of ``_native.c`` (``DK_COLLIDE_FIELDS``: the arguments of :func:`capsules_clear`)."""

    VERSION = 2
    _fields_ = _HEAD + [(name, _I64) for name in ("real_bytes", "N", "G", "P", "Wr", "H", "nthreads")] + \
        [(name, _PTR) for name in ("A", "B", "r", "pi", "pj", "wa", "wb", "wr", "hs", "skip_r", "skip_h")] + \
        [("margin", _F64), ("slack", _F64), ("ok", _PTR)] + \
        [(name, _I64) for name in ("Wb", "Wy", "nw")] + \
        [(name, _PTR) for name in ("wid", "bc", "bR", "bh", "ya", "yb", "yr", "skip_b", "skip_y", "point")]


class ClipArgs(ctypes.Structure):
    """``dk_clip`` of ``_native.c`` (``DK_CLIP_FIELDS``: the arguments of :func:`clip_rows`)."""

    VERSION = 3
    _fields_ = _HEAD + [(name, _I64) for name in
                        ("real_bytes", "nthreads", "N", "T", "nv", "ends", "K", "Ko", "P0", "P1")] + \
        [(name, _PTR) for name in
         ("kp", "kp_w", "x", "ko", "ko_w", "Rd", "feet", "pts", "rad", "contact", "support")] + \
        [(name, _F64) for name in ("w_contact", "w_pen", "w_flat", "w_skate", "ground")] + \
        [(name, _PTR) for name in ("Tf", "J", "fk", "cost", "D", "E", "g", "centre", "centre_jac")]


#: the structs checked at load, by the tag of their ``dk_layout_<tag>`` / ``dk_names_<tag>`` exports
STRUCTS: dict[str, type[ctypes.Structure]] = {"args": Args, "solve": SolveArgs, "watch": WatchArgs,
                                              "collide": Collide, "clip": ClipArgs}


def contiguous_as(t: Tensor, dtype: torch.dtype) -> Tensor:
    """``t`` as a contiguous tensor of ``dtype`` whose address a C call reads (itself, no copy and no op, in
    the common case where it is one already)."""
    return t if t.dtype == dtype and t.is_contiguous() else t.detach().to(dtype).contiguous()


def new_struct(struct_type: type[ctypes.Structure], **fields) -> ctypes.Structure:
    """A ``struct_type`` with its version and size set and ``fields`` set (tensors by their data pointer)."""
    return _filled(struct_type(version=struct_type.VERSION, size=ctypes.sizeof(struct_type)), **fields)


def _dlclose(handle: int) -> None:
    import _ctypes

    getattr(_ctypes, "dlclose", lambda h: None)(handle)


class AbiMismatch(RuntimeError):
    """The library's interface is not this module's: a struct of another version, size or layout, or
    another status code or limit (:data:`CONSTANTS`)."""


def _exported(lib, name: str, restype, argtypes):
    """The library's function ``name`` typed, or :class:`AbiMismatch` when it exports none (a library of
    another interface)."""
    try:
        fn = getattr(lib, name)
    except AttributeError:
        raise AbiMismatch(f"the native library exports no {name} (another interface)") from None
    fn.restype, fn.argtypes = restype, argtypes
    return fn


def check_layout(lib, tag: str, struct_type: type[ctypes.Structure], version: int | None = None) -> None:
    """Raise :class:`AbiMismatch` unless the library's struct ``tag`` (its ``dk_layout_<tag>`` and
    ``dk_names_<tag>``) has the version ``version`` (default ``struct_type.VERSION``), the size, field names
    and offsets of the ``ctypes.Structure`` ``struct_type``. The one check of every struct of the
    interface."""
    version = struct_type.VERSION if version is None else version
    fn = _exported(lib, f"dk_layout_{tag}", _I64, [_PTR, _I64])
    names = _exported(lib, f"dk_names_{tag}", ctypes.c_char_p, [])
    count = fn(None, 0)
    out = (_I64 * count)()
    fn(out, count)
    theirs = {"version": out[0], "size": out[1],
              "offsets": list(zip(names().decode().split(",")[:-1], out[3:]))}
    ours = {"version": version, "size": ctypes.sizeof(struct_type),
            "offsets": [(name, getattr(struct_type, name).offset) for name, *_ in struct_type._fields_]}
    if theirs != ours:
        diff = ", ".join(f"{k} {theirs[k]} (library) vs {ours[k]} (python)" for k in ours
                         if theirs[k] != ours[k] and k != "offsets")
        raise AbiMismatch(f"the native library's {tag} struct does not match {struct_type.__name__}: "
                          f"{diff or 'the field names or offsets differ'}")


def check_constants(lib, expected: dict[str, int] | None = None) -> None:
    """Raise :class:`AbiMismatch` unless the library's ``dk_constants`` hold every entry of ``expected``
    (default :data:`CONSTANTS`) with the same value."""
    expected = CONSTANTS if expected is None else expected
    fn = _exported(lib, "dk_constants", _I64, [_PTR, _I64])
    names = _exported(lib, "dk_constant_names", ctypes.c_char_p, [])
    count = fn(None, 0)
    out = (_I64 * count)()
    fn(out, count)
    theirs = dict(zip(names().decode().split(",")[:-1], out))
    wrong = [f"{k} {theirs.get(k, 'missing')} (library) vs {v} (python)" for k, v in expected.items()
             if theirs.get(k) != v]
    if wrong:
        raise AbiMismatch(f"the native library's constants differ: {', '.join(wrong)}")


def check_abi(lib) -> None:
    """Raise :class:`AbiMismatch` unless every struct of :data:`STRUCTS` (:func:`check_layout`), the
    constants (:func:`check_constants`) and the motions (:func:`motion_table`) of the library are this
    module's; then take the library's motion codes."""
    for tag, struct_type in STRUCTS.items():
        check_layout(lib, tag, struct_type)
    check_constants(lib)
    codes = motion_table(lib)
    _motion_codes.clear()
    _motion_codes.update(codes)


def motion_table(lib: ctypes.CDLL) -> dict[str, int]:
    """The library's codes of the elementary motions (``DK_MOTIONS``), checked against
    :data:`~diffkin.kernels.configuration.MOTION_NQ` / ``MOTION_NV``: every motion of the configuration
    layer, with the same nq and nv (else :class:`AbiMismatch`)."""
    fn = _exported(lib, "dk_motions", ctypes.c_char_p, [])
    rows = [r.split() for r in fn().decode().split(",")[:-1]]
    theirs = {letter: (int(nq), int(nv)) for letter, nq, nv in rows}
    ours = {m: (MOTION_NQ[m], MOTION_NV[m]) for m in MOTION_NQ}
    if theirs != ours:
        raise AbiMismatch(f"the native library's motions (letter: nq, nv) {theirs} are not the configuration "
                          f"layer's {ours}")
    return {letter: code for code, (letter, *_) in enumerate(rows)}


def _load(path: Path, flags: tuple[str, ...]) -> ctypes.CDLL:
    """Load the library at ``path`` and check its interface (:func:`check_abi`); a file that fails the check
    is compiled again once (a stale or foreign file under this name), then refused (:class:`AbiMismatch`).
    ``dk_fk`` takes a pointer to :class:`Args`, ``dk_solve`` one to :class:`SolveArgs`."""
    lib = ctypes.CDLL(str(path))
    try:
        check_abi(lib)
    except AbiMismatch:
        _dlclose(lib._handle)  # else dlopen hands back the loaded file for the same name
        path.unlink(missing_ok=True)
        lib = ctypes.CDLL(str(_compile(flags)))
        check_abi(lib)
    lib.dk_fk.restype, lib.dk_fk.argtypes = _I64, [ctypes.POINTER(Args)]
    lib.dk_solve.restype, lib.dk_solve.argtypes = _I64, [ctypes.POINTER(SolveArgs)]
    lib.dk_collide_clear.restype, lib.dk_collide_clear.argtypes = _I64, [ctypes.POINTER(Collide)]
    lib.dk_banded_solve.restype = _I64  # D, E, F, f_shared, g, shift, x, batch, T, n, real_bytes, nthreads
    lib.dk_banded_solve.argtypes = [_PTR] * 3 + [_I64] + [_PTR] * 3 + [_I64] * 5
    lib.dk_clip_rows.restype, lib.dk_clip_rows.argtypes = _I64, [ctypes.POINTER(ClipArgs)]
    lib.dk_clip_joint.restype, lib.dk_clip_joint.argtypes = _I64, [_PTR] * 6 + [_I64] * 8
    lib.dk_clip_step.restype, lib.dk_clip_step.argtypes = _I64, [_PTR] * 3 + [_I64] * 8
    lib.dk_spline_fine.restype, lib.dk_spline_fine.argtypes = _I64, [_PTR] * 4 + [_I64] * 6
    lib.dk_spline_marks.restype, lib.dk_spline_marks.argtypes = _I64, [_PTR] * 4 + [_I64] * 6
    lib.dk_topp_grid.restype = _I64  # in, x, B, M, n, big, real_bytes, nthreads
    lib.dk_topp_grid.argtypes = [_PTR] * 2 + [_I64] * 3 + [ctypes.c_double] + [_I64] * 2
    lib.dk_topp_sample.restype, lib.dk_topp_sample.argtypes = _I64, [_PTR] * 5 + [_I64] * 7
    lib.dk_topp_peaks.restype, lib.dk_topp_peaks.argtypes = _I64, [_PTR] * 3 + [_I64] * 8
    lib.dk_topp_slopes.restype, lib.dk_topp_slopes.argtypes = _I64, [_PTR] * 6 + [_I64] * 6
    return lib


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
    versions = sorted((tag, struct_type.VERSION) for tag, struct_type in STRUCTS.items())
    for part in (_SOURCE.read_bytes(), *(p.read_bytes() for p in _INCLUDED), f"abi {versions}".encode(),
                 " ".join(_FLAGS + flags).encode(),
                 _cpu_signature().encode(),
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
    with the compiler's message when no flag set compiles, :class:`AbiMismatch` (one) when the library
    built is not :class:`Args`'s (see :func:`check_abi`)."""
    global _lib, _tried, _error, _path
    with _lock:
        errors = []
        for flags in _OPTIONAL:
            try:
                path = _compile(flags)
                lib = _load(path, flags)
            except AbiMismatch as e:  # this module's layout, not the flags': no other flag set will do
                _tried, _error = True, str(e)
                raise
            except (RuntimeError, OSError, subprocess.SubprocessError) as e:
                errors.append(str(e))
                continue
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
    except AbiMismatch as e:  # built but not ours: said once (_tried); no compiler stays silent
        warnings.warn(f"diffkin's native kernel is not used, the torch kernels serve every call: {e}",
                      RuntimeWarning, stacklevel=2)
        return False
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


_SERIAL_MAX = CONSTANTS["SERIAL_MAX"]  # smaller batches never start a thread
_free = [0.0, 0]  # (time of the reading, free cores)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _own_running() -> int:
    """Threads of this process in state R (running or runnable) right now, the reader included: read from
    ``/proc/self/task/*/stat`` (the state is the field after the parenthesised command name)."""
    count = 0
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/stat") as f:
                stat = f.read()
        except OSError:  # the thread ended between the listing and the read
            continue
        count += stat[stat.rindex(")") + 2:].startswith("R")
    return max(count, 1)


def free_cores() -> int:
    """Cores of this process's affinity set not running another process's task right now (at least 1): the
    instantaneous runnable count of ``/proc/loadavg`` less this process's own runnable threads (the least
    of three readings in a row: a task that runs for an instant is no load), remembered for 0.1 s. Own
    threads are not load: torch's OpenMP workers spin for a while after each torch op, and counting them
    halved the threads of a C call that followed one (the batched IK solve ran 2.5x slower on an idle
    2-core machine). Without ``/proc`` (not Linux): every core."""
    now = time.monotonic()
    if now - _free[0] < 0.1:
        return _free[1]
    cores = _cores()
    try:
        others = cores
        for _ in range(3):  # the least of three readings: a task that runs for an instant is no load
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
            others = min(others, max(running - _own_running(), 0))
        free = max(1, cores - others)
    except (OSError, ValueError, IndexError):
        free = cores
    _free[0], _free[1] = now, free
    return free


_override = threading.local()  # .n: the count set by threads() on this thread (None: torch's)


@contextlib.contextmanager
def threads(n: int | None):
    """Within the block the C kernels called from this thread ask for ``n`` threads (``n ≥ 1``) instead of
    ``torch.get_num_threads()``, whatever the batch size, capped by :func:`free_cores` (module doc:
    thread policy); None leaves the policy as it is. Nests; torch's own thread count is not touched."""
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise OptionError(f"expected threads as an integer >= 1 or None, got {n!r}")
    before = getattr(_override, "n", None)
    _override.n = before if n is None else n
    try:
        yield
    finally:
        _override.n = before


def thread_count(batch: int, requested: int | None = None) -> int:
    """Threads the kernel uses for ``batch`` configurations: 1 up to 512, else ``requested`` (default
    ``torch.get_num_threads()``) capped by :func:`free_cores`; within :func:`threads` its count for any
    batch (capped the same way; see the module doc)."""
    forced = getattr(_override, "n", None) if requested is None else None
    if forced is None and batch <= _SERIAL_MAX:
        return 1
    requested = (forced or torch.get_num_threads()) if requested is None else requested
    return 1 if requested <= 1 or batch <= 1 else min(requested, batch, free_cores())


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
    """A chain's constants packed for the C kernel: the int32 structure and float64 / float32 reals, one
    tensor per array field of :class:`Args`, and a filled :class:`Args` per dtype (copied per call)."""

    __slots__ = ("ints", "reals", "head", "args", "n_ends", "n_vars", "n_velocities")

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
        ints = {"parent": topo.parents, "motion": _motions(topo), "qidx": topo.q_index,
                "vidx": _velocity_index(topo),
                "has_pre": [int(p is not None) for p in pre], "has_post": [int(p is not None) for p in post],
                "end_joint": topo.ends, "has_end": [int(E is not None) for E in seg.ends],
                "ancestor": [int(a) for row in topo.ancestors for a in row]}
        reals = {"mult": topo.multiplier, "qoff": [b + float(o or 0.0) for b, o in zip(topo.q_offset, off)],
                 "pre": [v for p in pre for v in rows(p)], "post": [v for p in post for v in rows(p)],
                 "base": rows(seg.base), "end": [v for E in seg.ends for v in rows(E)]}
        r64 = {name: torch.tensor(list(v), dtype=torch.float64) for name, v in reals.items()}
        self._link({name: torch.tensor(list(v), dtype=torch.int32) for name, v in ints.items()},
                   {torch.float64: r64, torch.float32: {k: v.to(torch.float32) for k, v in r64.items()}},
                   {"J": J, "K": K, "n": topo.n_vars, "nv": topo.n_dofs,
                    "has_base": int(seg.base is not None)})

    def _link(self, ints: dict, reals: dict, head: dict) -> None:
        """Keep the arrays and fill an :class:`Args` per dtype with their addresses."""
        self.ints, self.reals, self.head = ints, reals, head
        self.args = {dtype: new_struct(Args, real_bytes=dtype.itemsize, **head, **ints, **reals[dtype])
                     for dtype in reals}
        self.n_ends, self.n_vars, self.n_velocities = head["K"], head["n"], head["nv"]

    @property
    def euclidean(self) -> bool:
        """True when q and v are alike (every frame an R or P motion)."""
        return self.n_vars == self.n_velocities

    def __reduce__(self):  # copies and pickles carry the arrays; the addresses are made anew
        return _relinked, (self.ints, self.reals, self.head)

    def call(self, dtype: torch.dtype, **fields) -> Args:
        """A copy of this chain's :class:`Args` for ``dtype`` with one call's ``fields`` set."""
        return _filled(Args.from_buffer_copy(self.args[dtype]), **fields)


def _motions(topo: Topology) -> list[int]:
    """Per frame the library's code of its motion letter (:func:`motion_table`)."""
    if not _motion_codes:
        raise RuntimeError("the native library is not loaded (native.available() first)")
    return [_motion_codes[m] for m in topo.frame_motions]


def _velocity_index(topo: Topology) -> list[int]:
    """Per frame its first velocity, its (first) Jacobian column, from the column layout of ``topo``."""
    first: dict[int, int] = {}
    for j, v in zip(topo.column_frame, topo.column_v):
        first.setdefault(j, v)
    return [first[j] for j in range(topo.n_frames)]


def jacobian_support(topo: Topology, nv: int) -> Tensor:
    """``(K, nv)`` bool: the velocity columns each end link's Jacobian can be non-zero in (those of its
    ancestors' motions, as the FK writes them: column c of the frame layout into velocity ``column_v[c]``)."""
    sup = torch.zeros(len(topo.column_ancestors), nv, dtype=torch.bool)
    for k, row in enumerate(topo.column_ancestors):
        cols = [v for v, a in zip(topo.column_v, row) if a]
        sup[k, cols] = True
    return sup


def _relinked(ints: dict, reals: dict, head: dict) -> NativeModel:
    model = NativeModel.__new__(NativeModel)
    model._link(ints, reals, head)
    return model


def _filled(args: ctypes.Structure, **fields) -> ctypes.Structure:
    """``args`` with ``fields`` set, tensors by their data pointer (the caller keeps them alive)."""
    for name, v in fields.items():
        setattr(args, name, v.data_ptr() if isinstance(v, Tensor) else v)
    return args


def fk_jacobian(model: NativeModel, q: Tensor, with_jacobian: bool = False,
                threads: int | None = None) -> tuple[Tensor, Tensor | None, int]:
    """``q (B, nq)`` (CPU, float32/float64, contiguous) -> ``(T (B, K, 4, 4), J (B, K, 6, nv) or None,
    non-finite count)``: the end-link poses (2.50) and geometric Jacobians (3.30) (a ball motion's three
    columns: its angular velocity in the rotated frame, as the torch kernels). Rows whose q holds
    NaN/inf are not meaningful; the caller raises on a non-zero count. ``threads``: a fixed count instead of
    the policy of :func:`thread_count`."""
    B, nv, K = q.shape[0], model.n_velocities, model.n_ends
    T = q.new_empty(B, K, 4, 4)  # on q's device (the CPU), whatever the default device is
    J = q.new_empty(B, K, 6, nv) if with_jacobian else None
    args = model.call(q.dtype, batch=B, q=q, T=T, jac=J, nthreads=threads or thread_count(B))
    bad = _lib.dk_fk(ctypes.byref(args))
    _raise_on(bad, "frames")
    return T, J, bad


def _raise_on(status: int, what: str) -> None:
    if status == _ABI_ERROR:
        raise AbiMismatch("the native kernel refused the call's arguments (a struct of another version or "
                          "size)")
    if status == _RANGE_ERROR:
        raise OptionError(f"the native solve refused an option beyond its limits (library ranks above "
                          f"{CONSTANTS['MAX_RANKS']})")
    if status < 0:
        raise MemoryError(f"the native kernel could not allocate its per-thread {what}")


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



def solve_call(args: SolveArgs) -> None:
    """Run ``dk_solve`` (the whole IK solve, ``_native_solve.c``) on a filled :class:`SolveArgs` (its
    ``chain`` the address of a chain's filled :class:`Args`); raises on an allocation failure, an option
    beyond the library's limits (:class:`~diffkin.errors.OptionError`) or an interface mismatch."""
    _raise_on(_lib.dk_solve(ctypes.byref(args)), "work space")


def banded_solve(D: Tensor, E: Tensor, F: Tensor, g: Tensor, shift: Tensor | None = None) -> Tensor | None:
    """x ``(..., T, n)`` with H x = g for the block-banded SPD H of ``D, E, F (..., T, n, n)`` (the lower
    blocks of :func:`diffkin.kernels.banded.block_banded_solve`; ``shift (...)``: each system's D_t taken as
    D_t + shift I, without a copy of D), by ``dk_banded_solve`` (``_native_banded.c``); None (nothing done)
    where the library is not loaded, or the inputs are not CPU tensors of one float dtype without autograd.
    An ``F`` without batch dims (or broadcast ones of size 1) is passed once, shared by the systems (not
    copied batch times). Systems are shared between threads (:func:`thread_count` of the frames they
    hold)."""
    dtype = g.dtype
    given = [t for t in (D, E, F, shift) if t is not None]
    if (not available() or dtype not in (torch.float32, torch.float64) or torch.is_grad_enabled() and any(
            t.requires_grad for t in (*given, g)) or any(t.device.type != "cpu" or t.dtype != dtype
                                                        for t in given)):
        return None
    *lead, T, n = g.shape
    if g.numel() == 0:
        return torch.empty_like(g)
    shape = (*lead, T, n, n)
    D, E = (t.expand(shape).contiguous() for t in (D, E))
    f_shared = F.shape[:-3].numel() == 1  # one band for every system
    F = F.reshape(F.shape[-3:]).expand(T, n, n).contiguous() if f_shared else F.expand(shape).contiguous()
    g = g.contiguous()
    if shift is not None:
        shift = shift.expand(tuple(lead)).contiguous()
    x = torch.empty_like(g)
    batch = max(1, g.numel() // max(1, T * n))
    threads = min(batch, thread_count(batch * T))
    _raise_on(_lib.dk_banded_solve(D.data_ptr(), E.data_ptr(), F.data_ptr(), int(f_shared), g.data_ptr(),
                                   None if shift is None else shift.data_ptr(), x.data_ptr(), batch, T, n,
                                   g.element_size(), threads), "work space")
    return x


def _serves(dtype: torch.dtype, tensors) -> bool:
    """True when the library is loaded and every one of ``tensors`` (None skipped) is a CPU tensor of
    ``dtype`` (float32 or float64) without autograd: what the C twins of torch code below take."""
    return available() and dtype in (torch.float32, torch.float64) and all(
        t.device.type == "cpu" and t.dtype == dtype and not t.requires_grad for t in tensors if t is not None)


def _lanes(units: int, work: int) -> int:
    """Threads for ``units`` independent pieces (paths, clips) of ``work`` items in all: the policy of
    :func:`thread_count`, at most one per piece and at least one (OpenMP's num_threads must be positive)."""
    return max(1, min(units, thread_count(work)))


def _pointers(tensors) -> ctypes.Array:
    """The data pointers of ``tensors`` as a C array (NULL for None)."""
    return (ctypes.c_void_p * len(tensors))(*(None if t is None else t.data_ptr() for t in tensors))


def topp_grid(P1: Tensor, P2: Tensor, Q1: Tensor, Q2: Tensor, amax: Tensor, vmax: Tensor, delta: Tensor,
              stops: Tensor, big: float) -> Tensor | None:
    """x = ṡ² ``(B, M)`` of :func:`diffkin.trajectories.time_optimal._topp` from the path's derivatives
    by ``dk_topp_grid`` (``_native_topp.c``: its rows, their fixed bound, the moving row and the passes, per
    path; the same floats): ``P1, P2 (B, M, n)`` at the grid points, ``Q1, Q2 (B, M - 1, n)`` at the
    interval ends, ``amax, vmax (B, n)``, ``delta (B, M - 1)``, ``stops (B, M)`` bool, ``big`` the bound
    where no limit binds; None (nothing done) where the library is not loaded or the inputs are not CPU
    tensors of one float dtype without autograd. Paths are shared between threads."""
    ins = (P1, P2, Q1, Q2, amax, vmax, delta)
    dtype = P1.dtype
    if stops.device.type != "cpu" or not _serves(dtype, ins):
        return None
    B, M, n = P1.shape
    ins = [t.contiguous() for t in (*ins, stops.to(dtype))]
    x = torch.empty(B, M, dtype=dtype, device="cpu")  # C writes here: never the default device
    _raise_on(_lib.dk_topp_grid(_pointers(ins), x.data_ptr(), B, M, n, big, x.element_size(),
                                _lanes(B, B * M)), "work space")
    return x


def topp_slopes(knots: Tensor, coeffs: tuple[Tensor, ...], grid: Tensor, kseg: Tensor
                ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """The path's q', q'' of :func:`diffkin.trajectories.time_optimal._topp` by ``dk_topp_slopes``
    (``_native_topp.c``: _Path.eval's Horner, the same floats): ``P1, P2 (B, M, n)`` at the grid points
    ``grid (B, M)`` on their segments ``kseg (B, M)`` (right-hand at a knot) and ``Q1, Q2 (B, M - 1, n)``
    at each interval's end on its segment (left-hand), from the paths' ``knots (B, N)`` and coefficients
    ``c0..c3 (B, N - 1, n)``; None (nothing done) where the library is not loaded or the inputs are not CPU
    tensors of one float dtype without autograd. Paths are shared between threads."""
    ins = (knots, *coeffs, grid)
    dtype = grid.dtype
    if kseg.device.type != "cpu" or not _serves(dtype, ins):
        return None
    (B, M), N, n = grid.shape, knots.shape[1], coeffs[0].shape[-1]
    ins = [x.contiguous() for x in ins]
    kseg = kseg.to(torch.int64).expand(B, M).contiguous()
    P1, P2 = (torch.empty(B, M, n, dtype=dtype, device="cpu") for _ in range(2))  # C writes here
    Q1, Q2 = (torch.empty(B, M - 1, n, dtype=dtype, device="cpu") for _ in range(2))
    outs = [x.data_ptr() for x in (P1, P2, Q1, Q2)]
    _raise_on(_lib.dk_topp_slopes(_pointers(ins), kseg.data_ptr(), *outs, B, M, N, n, P1.element_size(),
                                  _lanes(B, B * M)), "work space")
    return P1, P2, Q1, Q2


def topp_peaks(t: Tensor, profile: tuple[Tensor, ...], tau: Tensor, k: Tensor, knots: Tensor,
               coeffs: tuple[Tensor, ...], limits: list[Tensor]) -> Tensor | None:
    """The peaks ``(B, len(limits))`` of :func:`diffkin.trajectories.time_optimal._peaks` (the largest
    |q̇| / v, |q̈| / a, |q⃛| / j of each path over the sample times ``t (B, T)``) by ``dk_topp_peaks``
    (``_native_topp.c``: the same floats), from the profile's knot times, grid, speeds and ∫s ``(B, M)`` and
    accelerations ``(B, M - 1)`` (``profile``), ``tau``, ``k (B,)``, the path's ``knots (B, N)`` and
    coefficients ``c0..c3 (B, N - 1, n)``, ``limits`` 2 or 3 of ``(B, n)``; None (nothing done) where the
    library is not loaded or the inputs are not CPU tensors of one float dtype without autograd. Paths are
    shared between threads."""
    ins = (t, *profile, tau, k, knots, *coeffs, *limits)
    dtype = t.dtype
    if len(limits) not in (2, 3) or not _serves(dtype, ins):
        return None
    (B, T), M, N, n = t.shape, profile[0].shape[1], knots.shape[1], coeffs[0].shape[-1]
    ins = [x.contiguous() for x in ins]
    peak = torch.empty(B, len(limits), dtype=dtype, device="cpu")  # C writes here: never the default device
    top = torch.empty(B, len(limits), n, dtype=dtype, device="cpu")
    _raise_on(_lib.dk_topp_peaks(_pointers(ins), top.data_ptr(), peak.data_ptr(), B, T, M, N, n, len(limits),
                                 peak.element_size(), _lanes(B, B * T)), "work space")
    return peak


def topp_sample(t: Tensor, rows: Tensor | None, profile: tuple[Tensor, ...], tau: Tensor, k: Tensor,
                knots: Tensor, coeffs: tuple[Tensor, ...], end: Tensor
                ) -> tuple[Tensor, Tensor, Tensor] | None:
    """q, q̇, q̈ ``(R, T, n)`` of :meth:`diffkin.trajectories.time_optimal.TimedPath._joint` at the times ``t
    (R, T)`` (``rows (R, T)``: the path of each sample; None: row r is path r) by ``dk_topp_sample``
    (``_native_topp.c``: the same floats), from the arrays of :func:`topp_peaks` and the paths' ends ``(B,
    n)``; None (nothing done) where the library is not loaded or the inputs are not CPU tensors of one float
    dtype without autograd."""
    ins = (t, *profile, tau, k, knots, *coeffs, end)
    dtype = t.dtype
    if (rows is not None and rows.device.type != "cpu") or not _serves(dtype, ins):
        return None
    (R, T), M, N, n = t.shape, profile[0].shape[1], knots.shape[1], end.shape[-1]
    ins = [x.contiguous() for x in ins]
    if rows is not None:
        rows = rows.to(torch.int64).expand(R, T).contiguous()
    q, qd, qdd = (torch.empty(R, T, n, dtype=dtype, device="cpu") for _ in range(3))  # C writes here
    _raise_on(_lib.dk_topp_sample(_pointers(ins), None if rows is None else rows.data_ptr(), q.data_ptr(),
                                  qd.data_ptr(), qdd.data_ptr(), R, T, M, N, n, q.element_size(),
                                  _lanes(R, R * T)), "work space")
    return q, qd, qdd


def spline_fine(u: Tensor, knots: Tensor, coeffs: tuple[Tensor, ...], end: Tensor, lo: Tensor, hi: Tensor,
                reach: Tensor) -> tuple[Tensor, Tensor] | None:
    """The fine samples of :func:`diffkin.motion._spline._spline_clear` by ``dk_spline_fine``
    (``_native_spline.c``: the same floats): from the fine samples ``u (F + 1)``, the splines' ``knots
    (B, N)``, coefficients ``c0..c3 (B, N - 1, n)`` and ends ``(B, n)``, the limits ``lo, hi`` and ``reach
    (n)``: the running bound-length ``cum (B, F + 1)`` and ``inside (B,)`` bool; None (nothing done) where
    the library is not loaded or the inputs are not CPU tensors of one float dtype without autograd."""
    ins = (u, knots, *coeffs, end, lo, hi, reach)
    dtype = u.dtype
    if not _serves(dtype, ins):
        return None
    (B, N), F, n = knots.shape, u.shape[0] - 1, end.shape[-1]
    ins = [x.contiguous() for x in ins]
    cpu = {"dtype": dtype, "device": "cpu"}  # C writes here: never the default device
    cum, inside, work = torch.empty(B, F + 1, **cpu), torch.empty(B, **cpu), torch.empty(B, 2 * n, **cpu)
    _raise_on(_lib.dk_spline_fine(_pointers(ins), cum.data_ptr(), inside.data_ptr(), work.data_ptr(), F, B, N,
                                  n, u.element_size(), _lanes(B, B * (F + 1))), "work space")
    return cum, inside > 0


def spline_marks(u: Tensor, cum: Tensor, step: Tensor, count: Tensor, first: Tensor, knots: Tensor,
                 coeffs: tuple[Tensor, ...], end: Tensor) -> Tensor | None:
    """The check points of :func:`diffkin.motion._spline._spline_clear` by ``dk_spline_marks``
    (``_native_spline.c``: the same floats): path b's marks ``m · step[b]`` (m = 0..count[b]) placed on its
    running length ``cum`` (:func:`spline_fine`) and its spline evaluated there, ``(Σ (count + 1), n)``,
    path b's from row ``first[b]``; None (nothing done) where :func:`spline_fine` would be."""
    ins = (u, cum, step, knots, *coeffs, end)
    dtype = u.dtype
    if any(x.device.type != "cpu" for x in (count, first)) or not _serves(dtype, ins):
        return None
    (B, N), F, n = knots.shape, u.shape[0] - 1, end.shape[-1]
    ins = [x.contiguous() for x in ins]
    count, first = count.to(torch.int64).contiguous(), first.to(torch.int64).contiguous()
    q = torch.empty(int(count.sum()) + B, n, dtype=dtype, device="cpu")  # C writes here
    _raise_on(_lib.dk_spline_marks(_pointers(ins), count.data_ptr(), first.data_ptr(), q.data_ptr(), F, B, N,
                                   n, u.element_size(), _lanes(B, q.shape[0])), "work space")
    return q


def clip_rows(Tf: Tensor | None, J: Tensor | None, *, T: int, keypoint_ends: list[int],
              keypoint_weights: Tensor, keypoints: Tensor, orientation_ends: list[int],
              orientation_weights: Tensor | None, orientations: Tensor | None, feet: list[int],
              soles: list[tuple[Tensor, Tensor]], contacts: Tensor, weights: dict, ground: float,
              out: tuple[Tensor, Tensor] | None = None, support: Tensor | None = None,
              fk: tuple[NativeModel, Tensor] | None = None, prepared: dict | None = None):
    """The frame terms of the whole-clip retargeting problem (:mod:`diffkin.retarget.whole_clip`: keypoints,
    orientations, the soles' contact height, penetration and level rows, skating) by ``dk_clip_rows``
    (``_native_clip.c``), from the end-link poses ``Tf (N, E, 4, 4)`` and Jacobians ``J (N, E, 6, nv)`` of
    N = B T frames (clips of ``T`` frames one after another): ``(cost (N,), D (N, nv, nv), E (N, nv, nv),
    g (N, nv))`` (cost ½‖r‖², D = JᵀJ, g = Jᵀr of each frame's rows, E the skating rows' block (t, t − 1)).
    ``keypoints (N, K, 3)`` of the ends ``keypoint_ends`` weighted by ``keypoint_weights (K,)``,
    ``orientations (N, K_o, 3, 3)`` of ``orientation_ends`` (or None), ``soles`` the feet's (points (P, 3),
    radii (P,)), ``contacts (N, 2)`` bool, ``weights`` the terms' weights by name. ``out``: optional
    ``(D, E)`` tensors to write D and E into (contiguous, of that shape and dtype; an iterative caller's
    buffers, which spares the allocator two fresh blocks per call). ``support``: optional ``(E, nv)`` bool,
    the columns each end link's Jacobian can be non-zero in (its ancestors': :func:`jacobian_support`; a
    column outside is taken as zero, a column inside that is zero adds exact zeros), else each frame's
    non-zero columns are found from its Jacobian. ``fk``: ``(model, q (N, nq))`` in place of ``Tf`` and ``J``
    (None): the frames' poses and Jacobians computed in the same pass, a block of frames at a time, instead
    of written out for all N frames and read back (the same values). ``prepared``: a dict an iterative
    caller keeps for one problem: the arguments other than the frames (keypoints to support) are converted
    for the C call once per dtype and kept there (later calls read them from it, not from the arguments).
    None (nothing done) where the library is not loaded or the inputs are not CPU tensors of one float dtype
    without autograd."""
    fused = Tf is None
    dtype = (fk[1] if fused else Tf).dtype
    if not _serves(dtype, (fk[1],) if fused else (Tf, J)):
        return None
    real = lambda t: t.detach().to(dtype).contiguous()  # noqa: E731
    longs = lambda v: torch.tensor(list(v), dtype=torch.int64)  # noqa: E731
    frames = real(fk[1] if fused else Tf)  # the configurations (N, nq) for the FK, or the poses (N, E, 4, 4)
    N = frames.shape[0]
    E, nv = (fk[0].n_ends, fk[0].n_velocities) if fused else (Tf.shape[1], J.shape[-1])
    Ko = len(orientation_ends)
    consts = None if prepared is None else prepared.get(dtype)
    if consts is None:
        consts = [longs(keypoint_ends), real(keypoint_weights), real(keypoints),
                  longs(orientation_ends or [0]), real(orientation_weights if Ko else frames.new_zeros(1)),
                  real(orientations if Ko else frames.new_zeros(1)), longs(feet),
                  real(torch.cat([s[0] for s in soles])), real(torch.cat([s[1] for s in soles])),
                  contacts.to(torch.uint8).contiguous(),
                  None if support is None else support.to(device="cpu", dtype=torch.uint8).contiguous()]
        if prepared is not None:
            prepared[dtype] = consts
    keep = [None if fused else frames, None if fused else real(J), *consts]
    chain_args = fk[0].call(dtype, batch=N, q=frames, nthreads=1) if fused else None
    cost, g = frames.new_empty(N), frames.new_empty(N, nv)
    if out is not None and all(t.shape == (N, nv, nv) and t.dtype == dtype and t.device.type == "cpu"
                               and t.is_contiguous() for t in out):
        D, Eb = out
    else:
        D, Eb = frames.new_empty(N, nv, nv), frames.new_empty(N, nv, nv)
    centre, centre_jac = frames.new_empty(N, 4), frames.new_empty(N, 4, nv)
    threads = thread_count(N)
    args = new_struct(ClipArgs, real_bytes=frames.element_size(), nthreads=threads, N=N, T=T, nv=nv,
                      ends=E, K=len(keypoint_ends), Ko=Ko, P0=soles[0][0].shape[0], P1=soles[1][0].shape[0],
                      kp=keep[2], kp_w=keep[3], x=keep[4], ko=keep[5], ko_w=keep[6], Rd=keep[7], feet=keep[8],
                      pts=keep[9], rad=keep[10], contact=keep[11], support=keep[12],
                      w_contact=float(weights["contact_height"]),
                      w_pen=float(weights["penetration"]), w_flat=float(weights["flat_foot"]),
                      w_skate=float(weights["skating"]), ground=float(ground), Tf=keep[0], J=keep[1],
                      fk=None if chain_args is None else ctypes.addressof(chain_args), cost=cost, D=D, E=Eb,
                      g=g, centre=centre, centre_jac=centre_jac)
    _raise_on(_lib.dk_clip_rows(ctypes.byref(args)), "work space")
    return cost, D, Eb, g


def clip_joint(q: Tensor, q_ref: Tensor, space, lo: Tensor, hi: Tensor, vstep: Tensor | None,
               weights: Tensor, cost: Tensor, D: Tensor, E: Tensor, g: Tensor) -> bool:
    """The joint terms of the whole-clip retargeting problem (:meth:`diffkin.retarget.whole_clip._Terms.
    _joint_terms`: limits and velocity limits on the scalar coordinates, posture, velocity and acceleration
    rows) of ``q (B, T, nq)`` with the posture reference ``q_ref (B, T, nq)`` added in place to ``cost
    (B,)``, ``D, E (B, T, nv, nv)`` and ``g (B, T, nv)`` (contiguous) by ``dk_clip_joint``
    (``_native_clip.c``; the differences ⊖ of ``space``, a
    :class:`~diffkin.kernels.configuration.ConfigurationSpace`, formed there), with the soft limits ``lo, hi
    (ns,)`` and ``vstep (ns,)`` (q̇_max / fps; None: no velocity limits) of its ns scalar coordinates and
    ``weights (5,)`` (limit, velocity_limit, posture, velocity, acceleration). False (nothing done) where the
    library is not loaded or the tensors are not CPU tensors of one float dtype without autograd. Clips are
    shared between threads."""
    if (not all(t.is_contiguous() for t in (cost, D, E, g))
            or not _serves(D.dtype, (q, q_ref, lo, hi, vstep, weights, cost, D, E, g))):
        return False
    B, T, nq = q.shape
    ins = [t.contiguous() for t in (q, q_ref.expand(q.shape), lo, hi)] + [
        None if vstep is None else vstep.contiguous(), weights.contiguous()]
    idx = _space_index(space)
    _raise_on(_lib.dk_clip_joint(_pointers(ins), _pointers(idx), cost.data_ptr(), D.data_ptr(), E.data_ptr(),
                                 g.data_ptr(), B, T, nq, D.shape[-1], len(idx[0]), len(idx[2]) // 4,
                                 D.element_size(), _lanes(B, B * T)), "work space")
    return True


def _space_index(space) -> list[Tensor]:
    """(sq, sv, bq, bv) of a :class:`~diffkin.kernels.configuration.ConfigurationSpace` as int64 CPU tensors
    (the scalar coordinates' q and v columns, the quaternions' four q and three v columns each), made once per
    space."""
    made = space._cache.get("native_index")
    if made is None:
        quats_q, quats_v = space.quaternion_index("q"), space.quaternion_index("v")
        made = [torch.tensor(list(v), dtype=torch.int64, device="cpu") for v in (
            space.scalar_index("q"), space.scalar_index("v"), [i for b in quats_q for i in b],
            [i for b in quats_v for i in b])]
        space._cache["native_index"] = made
    return made


def clip_step(q: Tensor, step: Tensor, space, q_limits: tuple[Tensor, Tensor], limits: tuple[Tensor, Tensor],
              vstep: Tensor | None) -> Tensor | None:
    """The whole-clip step of :func:`diffkin.retarget.optimize_clip` by ``dk_clip_step`` (``_native_clip.c``):
    ``q (B, T, nq)`` ⊕ ``step (B, T, nv)`` (``space``'s integrate), clamped to ``q_limits`` (lower, upper
    ``(nq,)``), then frame after frame the ns scalar coordinates onto their velocity limits ``vstep (ns,)``
    (q̇_max / fps; None: none) within ``limits`` (lower, upper ``(ns,)``): ``(B, T, nq)``. None (nothing
    done) where the library is not loaded or the inputs are not CPU tensors of one float dtype without
    autograd. Clips are shared between threads."""
    dtype = q.dtype
    if not _serves(dtype, (q, step, *q_limits, *limits, vstep)):
        return None
    B, T, nq = q.shape
    ins = [t.contiguous() for t in (q, step, *q_limits, *limits)]
    ins.append(None if vstep is None else vstep.contiguous())
    idx = _space_index(space)
    out = torch.empty(B, T, nq, dtype=dtype, device="cpu")  # C writes here: never the default device
    _raise_on(_lib.dk_clip_step(_pointers(ins), _pointers(idx), out.data_ptr(), B, T, nq, step.shape[-1],
                                len(idx[0]), len(idx[2]) // 4, q.element_size(), _lanes(B, B * T)),
              "work space")
    return out


def capsules_clear(A: Tensor, B: Tensor, r: Tensor, pairs: Tensor, round_objects, halfspaces: Tensor,
                   skip_round: Tensor | None, skip_half: Tensor | None, margin: float, slack: float,
                   ok: Tensor, *, boxes=None, cylinders=None, skip_box: Tensor | None = None,
                   skip_cylinder: Tensor | None = None, points: Tensor | None = None,
                   world_index: Tensor | None = None) -> bool:
    """Clear ``ok (N,)`` (bool, in place) where a checked distance has d − margin < slack: capsules with
    ends ``A, B (G, 3, N)`` (contiguous, component-major) and radii ``r (G,)``, the self ``pairs (P, 2)``
    (long), the round world objects ``(a (W, 3), b (W, 3), r (W,))`` (spheres, capsules, points as
    capsules), ``halfspaces (H, 4)`` (``{x : n·x ≤ offset}``), ``boxes`` ``(c (W_b, 3), R (W_b, 3, 3), h
    (W_b, 3))`` and ``cylinders`` ``(a (W_y, 3), b (W_y, 3), r (W_y,))`` — cylinders against the capsules
    that ``points (G,)`` (bool) marks as spheres only, none without ``points`` — with the entries
    ``skip_*`` (``(G, W)``, ``(G, H)``, ``(G, W_b)``, ``(G, W_y)`` bool) left out. Boxes against proper
    segments need margin + slack >= 0 (the caller's contract: a penetration depth is not computed).

    One world for all configurations, or ``nw`` worlds: every object tensor with a leading ``(nw, ...)``
    dim (:meth:`~diffkin.collision.World.stack`) and ``world_index (N,)`` (long) the world of each
    configuration. One call of ``dk_collide_clear`` (``_native_collide.c``); False (nothing done) where the
    library is not loaded or the inputs are not CPU tensors of one float dtype."""
    made = collide_struct(A, B, r, pairs, round_objects, halfspaces, skip_round, skip_half, margin, slack, ok,
                          boxes=boxes, cylinders=cylinders, skip_box=skip_box, skip_cylinder=skip_cylinder,
                          points=points, world_index=world_index)
    return made is not None and _lib.dk_collide_clear(ctypes.byref(made[0])) == 0


def collide_struct(A: Tensor, B: Tensor, r: Tensor, pairs: Tensor, round_objects, halfspaces: Tensor,
                   skip_round: Tensor | None, skip_half: Tensor | None, margin: float, slack: float,
                   ok: Tensor | None, *, boxes=None, cylinders=None, skip_box: Tensor | None = None,
                   skip_cylinder: Tensor | None = None, points: Tensor | None = None,
                   world_index: Tensor | None = None) -> tuple[Collide, list] | None:
    """The :class:`Collide` of a :func:`capsules_clear` call (same arguments; ``ok`` None: no output) and the
    tensors its addresses point into (keep them alive while it is used), or None where the library does not
    serve the inputs (not loaded, not CPU tensors of one float dtype). The planner's C search
    (``dk_plan_search``) takes it as the constants of its decisions."""
    dtype = A.dtype
    if not available() or A.device.type != "cpu" or dtype not in (torch.float32, torch.float64):
        return None
    real = lambda t: contiguous_as(t, dtype)  # noqa: E731
    empty = lambda *s: A.new_zeros(*s)  # noqa: E731
    wa, wb, wr = (real(t) for t in round_objects)
    hs = real(halfspaces)
    boxes = boxes if boxes is not None else (empty(0, 3), empty(0, 3, 3), empty(0, 3))
    cylinders = cylinders if cylinders is not None else (empty(0, 3), empty(0, 3), empty(0))
    bc, bR, bh = (real(t) for t in boxes)
    ya, yb, yr = (real(t) for t in cylinders)
    nw = next((t.shape[0] for t in (wa, hs, bc, ya) if t.ndim == 3), 1)
    keep = [A, B, real(r), pairs[:, 0].contiguous(), pairs[:, 1].contiguous(), wa, wb, wr, hs, bc, bR, bh,
            ya, yb, yr]
    skips = [None if m is None else m.to(torch.uint8).contiguous()
             for m in (skip_round, skip_half, skip_box, skip_cylinder, points)]
    wid = None if world_index is None else world_index.to(torch.int64).contiguous()
    ptr = lambda t: None if t is None or t.numel() == 0 else t.data_ptr()  # noqa: E731
    okb = None if ok is None else ok.view(torch.uint8)
    c = new_struct(Collide, real_bytes=A.element_size(), N=A.shape[-1], G=A.shape[0], P=pairs.shape[0],
                   Wr=wa.shape[-2], H=hs.shape[-2],
                   nthreads=thread_count(A.shape[-1] * max(1, pairs.shape[0]) // 64),
                   A=A.data_ptr(), B=B.data_ptr(), r=ptr(keep[2]), pi=ptr(keep[3]), pj=ptr(keep[4]),
                   wa=ptr(wa), wb=ptr(wb), wr=ptr(wr), hs=ptr(hs), skip_r=ptr(skips[0]), skip_h=ptr(skips[1]),
                   margin=float(margin), slack=float(slack), ok=ptr(okb),
                   Wb=bc.shape[-2], Wy=ya.shape[-2], nw=nw, wid=ptr(wid), bc=ptr(bc), bR=ptr(bR), bh=ptr(bh),
                   ya=ptr(ya), yb=ptr(yb), yr=ptr(yr), skip_b=ptr(skips[2]), skip_y=ptr(skips[3]),
                   point=ptr(skips[4]))
    return c, [*keep, *skips, wid, okb]
