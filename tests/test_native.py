"""The fused native kernel (diffkin.kernels.native) against the torch kernels it stands in for: every joint
kind, trees with several end links, mimic joints, base and tool, both dtypes, any batch shape, threads;
non-finite input, far angles, the fallback and the build."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import warnings

import pytest
import torch

from diffkin import models
from diffkin.errors import NonFiniteError
from diffkin.kernels import native
from tests.helpers import native_chain, stand_in_compiler

pytestmark = pytest.mark.skipif(not native.available(),
                                reason="no C compiler: the native kernel is not built")

TOL = {torch.float64: 1e-12, torch.float32: 5e-6}


KINDS = ["panda", "ur5", "stanford", "panda_base_tool", "allegro", "yumi_mimic", "tiago"]


def _reference(chain, q):
    with native.disabled(), torch.no_grad():
        return chain.forward_kinematics(q), chain.forward_kinematics_and_jacobian(q)[1]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("kind", KINDS)
def test_native_equals_the_torch_kernels(kind, dtype):
    chain = native_chain(kind, dtype)
    gen = torch.Generator().manual_seed(1)
    for shape in [(), (1,), (3, 5), (700,)]:  # 700 > the serial limit: several threads
        q = chain.random_configuration(shape, generator=gen)
        T_ref, J_ref = _reference(chain, q)
        with torch.no_grad():
            assert chain._native_model(q) is not None
            T = chain.forward_kinematics(q)
            T2, J = chain.forward_kinematics_and_jacobian(q)
        assert T.shape == T_ref.shape and J.shape == J_ref.shape and T.dtype == dtype
        torch.testing.assert_close(T, T_ref, atol=TOL[dtype], rtol=0)
        torch.testing.assert_close(T2, T_ref, atol=TOL[dtype], rtol=0)
        torch.testing.assert_close(J, J_ref, atol=TOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_batch_last_layout_matches(dtype):
    chain = native_chain("allegro", dtype)
    qT = chain.random_configuration((37,), generator=torch.Generator().manual_seed(2)).T.contiguous()
    with torch.no_grad():
        rows, ends = chain.batch_last(qT, with_jacobian=True)
        with native.disabled():
            rows_ref, ends_ref = chain.batch_last(qT, with_jacobian=True)
    torch.testing.assert_close(rows, rows_ref, atol=TOL[dtype], rtol=0)
    for frame, frame_ref in zip(ends, ends_ref):
        for col, col_ref in zip(frame, frame_ref):
            torch.testing.assert_close(col, col_ref.expand_as(col), atol=TOL[dtype], rtol=0)


def test_threads_do_not_change_a_value():
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((5000,), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        packed = chain._native_model(q)
    one = native.fk_jacobian(packed, q, True, threads=1)
    two = native.fk_jacobian(packed, q, True, threads=2)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_empty_batch_and_far_angles():
    chain = models.load("ur5", dtype=torch.float64)
    with torch.no_grad():
        assert chain.forward_kinematics(torch.zeros(0, 6, dtype=torch.float64)).shape == (0, 4, 4)
        # |q| >= 1e5 rad: libm's full range reduction, as torch does
        q = torch.tensor([[1e5, -3e6, 0.3, 1e9, 2.0, -1e7]], dtype=torch.float64)
        T_ref, J_ref = _reference(chain, q)
        torch.testing.assert_close(chain.forward_kinematics(q), T_ref, atol=1e-12, rtol=0)
        torch.testing.assert_close(chain.forward_kinematics_and_jacobian(q)[1], J_ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("scale", [3.0, 5e3, 2e4])  # float reduction; |q| >= 1e4: the double one
def test_float_sin_cos_near_and_far(scale):
    """The float FK's own sin/cos (8 lanes) against the torch float32 kernels, and against float64: no
    worse than torch's float32 error."""
    chain, c64 = models.load("panda", dtype=torch.float32), models.load("panda", dtype=torch.float64)
    gen = torch.Generator().manual_seed(13)
    q = ((torch.rand(3000, 7, generator=gen) * 2 - 1) * scale).float()
    with torch.no_grad():
        T, J = chain.forward_kinematics_and_jacobian(q)
        with native.disabled():
            T_ref, J_ref = chain.forward_kinematics_and_jacobian(q)
        T64 = c64.forward_kinematics(q.double())
    torch.testing.assert_close(T, T_ref, atol=5e-6, rtol=0)
    torch.testing.assert_close(J, J_ref, atol=5e-6, rtol=0)
    assert (T.double() - T64).abs().max() <= 2 * (T_ref.double() - T64).abs().max()


def test_non_finite_q_raises_or_stays_in_its_row():
    chain = models.load("panda", dtype=torch.float32)
    q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(4))
    q[2, 3] = float("nan")
    with torch.no_grad():
        with pytest.raises(NonFiniteError, match="q"):
            chain.forward_kinematics(q)
        with pytest.raises(NonFiniteError, match="q"):
            chain.forward_kinematics_and_jacobian(q)
        T = chain.forward_kinematics(q, check=False)
        with native.disabled():
            T_ref = chain.forward_kinematics(q, check=False)
    assert torch.isnan(T[2]).any() and torch.isfinite(T[[0, 1, 3]]).all()
    torch.testing.assert_close(T[[0, 1, 3]], T_ref[[0, 1, 3]], atol=5e-6, rtol=0)


def test_gradients_keep_the_torch_kernels():
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(5)).requires_grad_(True)
    assert chain._native_model(q) is None  # q needs a gradient
    T = chain.forward_kinematics(q)
    assert T.grad_fn is not None
    chain.requires_grad_(False)
    assert chain._native_model(q.detach()) is not None
    with torch.no_grad():
        assert chain._native_model(q) is not None


def test_parameter_updates_reach_the_native_constants():
    chain = models.load("ur5", dtype=torch.float64)
    q = chain.random_configuration((5,), generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        before = chain.forward_kinematics(q)
        chain.a[1] += 0.01  # in place: a new version of the parameter
        after = chain.forward_kinematics(q)
        ref = _reference(chain, q)[0]
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, ref, atol=1e-12, rtol=0)


def test_disabled_and_missing_compiler(monkeypatch, tmp_path):
    with native.disabled():
        assert not native.available()
    assert native.available()
    monkeypatch.setenv("DIFFKIN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "no-such-compiler")
    monkeypatch.setattr(native.shutil, "which", lambda name: None)
    with pytest.raises(RuntimeError, match="no C compiler"):
        native._compile(())
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_build_into_a_fresh_cache_and_the_command(tmp_path):
    # the command's build path with the session's library as the compiler's output (a real compile costs
    # about 35 s; make test's `python -m diffkin.kernels` before the suite is the real one)
    if not native.available():
        pytest.skip("the C library is not built (no compiler): nothing to stand in for")
    env = {**os.environ, "DIFFKIN_CACHE_DIR": str(tmp_path / "cache"), "CC": stand_in_compiler(tmp_path)}
    out = subprocess.run([sys.executable, "-m", "diffkin.kernels"], env=env, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr
    built = list((tmp_path / "cache").glob("diffkin_native-*.so"))
    assert len(built) == 1 and str(built[0]) in out.stdout
    off = subprocess.run([sys.executable, "-m", "diffkin.kernels"], capture_output=True, text=True,
                         env={**env, "DIFFKIN_NATIVE": "0"})
    assert "disabled" in off.stdout


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_own_running_threads_are_counted():
    # a thread of this process computing outside the GIL is runnable: it and the reader are two
    import threading

    done, started = threading.Event(), threading.Event()

    def busy():
        a = torch.randn(300, 300, dtype=torch.float64)
        started.set()
        while not done.is_set():
            a = torch.tanh(a @ a)

    worker = threading.Thread(target=busy)
    with torch.no_grad():
        worker.start()
        started.wait(10)
        counts = [native._own_running() for _ in range(20)]
        done.set()
        worker.join()
    assert min(counts) >= 1 and max(counts) >= 2


def test_thread_policy_counts_free_cores(monkeypatch):
    # free cores = the affinity set less the runnable tasks of /proc/loadavg (field 4: running/total) that
    # are not this process's own runnable threads (the reader and, say, torch's spinning OpenMP workers)
    import io

    monkeypatch.setattr(native, "_cores", lambda: 4)
    for running, own, free in ((1, 1, 4), (3, 1, 2), (9, 1, 1), (3, 3, 4), (5, 2, 1)):
        monkeypatch.setattr(native, "_free", [-1e9, 0])  # no remembered reading
        monkeypatch.setattr(native, "_own_running", lambda o=own: o)
        monkeypatch.setattr(native, "open", lambda *a, r=running, **k: io.StringIO(f"0.5 0.4 0.3 {r}/300 42"),
                            raising=False)
        assert native.free_cores() == free
    monkeypatch.setattr(native, "_free", [-1e9, 0])
    monkeypatch.setattr(native, "open", lambda *a, **k: (_ for _ in ()).throw(OSError("no /proc")),
                        raising=False)
    assert native.free_cores() == 4  # without /proc: every core
    monkeypatch.undo()
    assert 1 <= native.free_cores() <= max(1, os.cpu_count() or 1)
    assert native.thread_count(512, 8) == 1  # small batches: the calling thread only
    assert native.thread_count(10**6, 1) == 1
    monkeypatch.setattr(native.time, "monotonic", lambda: 1e9)  # the remembered reading is fresh
    monkeypatch.setattr(native, "_free", [1e9, 1])  # one core free: another process holds the other
    assert native.thread_count(10**6, 2) == 1
    monkeypatch.setattr(native, "_free", [1e9, 3])
    assert native.thread_count(10**6, 2) == 2 and native.thread_count(10**6, 8) == 3
    # within native.threads(n): n for batches of any size (not torch's count), capped by the free cores
    with native.threads(2):
        assert native.thread_count(10) == 2 and native.thread_count(1) == 1
        assert native.thread_count(10, 1) == 1  # an explicit request still wins
        with native.threads(8):
            assert native.thread_count(10**6) == 3
        with native.threads(None):  # None: the setting around it
            assert native.thread_count(10) == 2
        assert native.thread_count(10**6) == 2
    assert native.thread_count(10) == 1  # restored: small batches on the calling thread again
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="threads"), native.threads(bad):
            pass
    # an explicit count is used as given, and the values do not depend on it
    chain = models.load("panda", dtype=torch.float32)
    q = chain.random_configuration((2000,), generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        packed = chain._native_model(q)
    assert torch.equal(native.fk_jacobian(packed, q, threads=1)[0], native.fk_jacobian(packed, q)[0])


def test_free_cores_reads_loadavg(monkeypatch, tmp_path):
    fake = tmp_path / "loadavg"
    fake.write_text("1.00 1.00 1.00 2/100 999\n")  # the reader and one other runnable task
    real_open = open
    monkeypatch.setattr(native, "_free", [0.0, 0])
    monkeypatch.setattr(native, "_cores", lambda: 2)
    monkeypatch.setattr("builtins.open", lambda p, *a, **k: real_open(fake if p == "/proc/loadavg" else p,
                                                                        *a, **k))
    assert native.free_cores() == 1
    fake.write_text("0.10 0.10 0.10 1/100 999\n")
    monkeypatch.setattr(native, "_free", [0.0, 0])
    assert native.free_cores() == 2


# ------------------------------------------------------------------------------ the C solve
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_solve_with_the_c_backend_matches_the_torch_one(dtype):
    from diffkin import ik

    chain = models.load("panda", dtype=dtype)
    q = chain.random_configuration((200,), generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
        fused = ik.solve(chain, T, seed=0)
        with native.disabled():
            ref = ik.solve(chain, T, seed=0)
    assert fused.success.float().mean() >= 0.99 and ref.success.float().mean() >= 0.99
    ok = fused.success
    assert (fused.position_error[ok] <= 1e-4).all() and (fused.orientation_error[ok] <= 1e-3).all()
    # one algorithm in C and in torch: the same flags and iteration counts, the same solutions to rounding
    # (float64: 5e-13 measured); float32 rounds the two LM steps differently, and a convergence or stall
    # test may then fall one step apart (1 of 200 targets measured; q within 3e-4 where the counts agree)
    assert torch.equal(fused.success, ref.success)
    same = fused.iterations == ref.iterations
    if dtype == torch.float64:
        assert bool(same.all())
        torch.testing.assert_close(fused.q, ref.q, atol=1e-9, rtol=0)
        torch.testing.assert_close(fused.position_error, ref.position_error, atol=1e-11, rtol=0)
    else:
        assert float(same.float().mean()) >= 0.97
        torch.testing.assert_close(fused.q[same], ref.q[same], atol=1e-3, rtol=0)


# ------------------------------------------------------------------------------ the versioned interface
def _struct_like(struct_type, fields):
    return type("Mismatched" + struct_type.__name__, (ctypes.Structure,), {"_fields_": fields})


@pytest.mark.parametrize("tag", sorted(native.STRUCTS))
def test_the_library_speaks_this_modules_interface(tag):
    """Every struct of the interface (FK, solve, watch, collide) is checked by the one generic check:
    its version, its size (a field missing) and its field names and offsets (two fields swapped)."""
    native.check_abi(native._lib)  # the loaded library: every struct, the constants, the motions
    struct_type = native.STRUCTS[tag]
    fields, v = list(struct_type._fields_), struct_type.VERSION
    native.check_layout(native._lib, tag, struct_type)
    with pytest.raises(native.AbiMismatch, match=f"{tag} struct .* version {v} .library. vs {v + 1}"):
        native.check_layout(native._lib, tag, struct_type, v + 1)
    with pytest.raises(native.AbiMismatch, match="size"):  # a field missing
        native.check_layout(native._lib, tag, _struct_like(struct_type, fields[:-1]), v)
    swapped = [*fields[:2], fields[3], fields[2], *fields[4:]]  # same size, other names at the offsets
    with pytest.raises(native.AbiMismatch, match="names or offsets"):
        native.check_layout(native._lib, tag, _struct_like(struct_type, swapped), v)
    with pytest.raises(native.AbiMismatch, match="exports no dk_layout_nothing"):
        native.check_layout(native._lib, "nothing", struct_type)


def test_a_solver_option_leaves_the_fk_struct_alone():
    """The FK's dk_args holds the chain and one FK call only: every solve field lives in dk_solve_args."""
    fk = {name for name, *_ in native.Args._fields_}
    solve = {name for name, *_ in native.SolveArgs._fields_}
    assert fk & solve == {"version", "size", "nthreads"} and "chain" in solve  # the chain: an address
    assert {"damping2", "lib_ranks", "n_seeds", "q_out"} <= solve


def test_the_constants_check_catches_a_changed_constant():
    """The status codes and limits Python uses are the library's (dk_constants): a changed or missing one
    is refused, and the codes the entry points return are those of the table."""
    native.check_constants(native._lib)
    with pytest.raises(native.AbiMismatch, match=r"DK_STALE -4 \(library\) vs -7 \(python\)"):
        native.check_constants(native._lib, {**native.CONSTANTS, "DK_STALE": -7})
    with pytest.raises(native.AbiMismatch, match=r"MAX_RANKS 64 \(library\) vs 32"):
        native.check_constants(native._lib, {**native.CONSTANTS, "MAX_RANKS": 32})
    with pytest.raises(native.AbiMismatch, match="DK_GONE missing"):
        native.check_constants(native._lib, {"DK_GONE": 1})
    codes = [native.CONSTANTS[k] for k in ("DK_ABI_ERROR", "DK_RANGE_ERROR", "DK_STALE", "DK_NOT_RIGID")]
    assert len(set(codes)) == 4 and all(c < -1 for c in codes)  # distinct from 0, counts and -1 (memory)


def _panda_call(n=3):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(11))
    with torch.no_grad():
        packed = chain._native_model(q)
    return chain, q, packed


def test_the_kernel_refuses_a_struct_of_another_version_or_size():
    chain, q, packed = _panda_call()
    T = torch.zeros(3, 1, 4, 4, dtype=torch.float64)
    lib, abi_error = native._lib, native.CONSTANTS["DK_ABI_ERROR"]
    for wrong in ({"version": native.ABI_VERSION + 1}, {"size": ctypes.sizeof(native.Args) - 8},
                  {"real_bytes": 2}):
        args = packed.call(torch.float64, batch=3, q=q, T=T, jac=None, nthreads=1, **wrong)
        assert lib.dk_fk(ctypes.byref(args)) == abi_error
        assert not T.any()  # nothing written
    args = packed.call(torch.float64, batch=3, q=q, T=T, jac=None, nthreads=1)
    assert lib.dk_fk(ctypes.byref(args)) == 0
    with native.disabled(), torch.no_grad():
        torch.testing.assert_close(T[:, 0], chain.forward_kinematics(q), atol=1e-12, rtol=0)
    with pytest.raises(native.AbiMismatch, match="refused the call"):
        native._raise_on(abi_error, "frames")


@pytest.mark.parametrize("wrong", ["version", "size"])
def test_the_solve_watch_and_collide_entries_refuse_a_struct_of_another_version_or_size(wrong):
    """dk_solve, dk_solve_one, dk_fk_one, dk_unchanged and dk_collide_clear check their own structs at call
    time: nothing is computed or written, DK_ABI_ERROR is returned (AbiMismatch through solve_call)."""
    from diffkin.kernels import single

    chain, q, packed = _panda_call()
    lib, abi_error = native._lib, native.CONSTANTS["DK_ABI_ERROR"]
    off = {"version": lambda s: s.VERSION + 1, "size": lambda s: ctypes.sizeof(s) - 8}[wrong]
    T = chain.forward_kinematics(q).contiguous()
    out = torch.full((3, 7), 7.0, dtype=torch.float64)
    chain_args = packed.args[torch.float64]
    solve = native.new_struct(native.SolveArgs, chain=ctypes.addressof(chain_args), n_targets=3, nthreads=1,
                              q_out=out)
    setattr(solve, wrong, off(native.SolveArgs))
    assert lib.dk_solve(ctypes.byref(solve)) == abi_error
    with pytest.raises(native.AbiMismatch):
        native.solve_call(solve)
    bad_chain = native.Args.from_buffer_copy(chain_args)
    setattr(bad_chain, wrong, off(native.Args))
    good = native.new_struct(native.SolveArgs, chain=ctypes.addressof(bad_chain), n_targets=3, nthreads=1,
                             q_out=out)
    assert lib.dk_solve(ctypes.byref(good)) == abi_error  # a good solve struct on a chain of another layout
    assert torch.all(out == 7.0)  # nothing written

    watch = single.Watch([q])
    assert watch.unchanged()
    fk_one, unchanged, solve_one = lib.dk_fk_one, lib.dk_unchanged, lib.dk_solve_one
    fk_one.restype, fk_one.argtypes = ctypes.c_int64, [ctypes.c_void_p] * 5
    unchanged.restype, unchanged.argtypes = ctypes.c_int64, [ctypes.c_void_p]
    solve_one.restype = ctypes.c_int64
    solve_one.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64] + \
        [ctypes.c_void_p] * 6
    one = [out[0].data_ptr()] + [out[1].data_ptr()] * 5  # q, ok, pe, oe, its, seeds: none may be written
    good.chain = ctypes.addressof(chain_args)
    for sol, w in ((solve, watch), (good, None)):  # a bad solve struct; a bad watch (made so below)
        if w is None:
            setattr(watch.c, wrong, off(native.WatchArgs))
        assert solve_one(ctypes.addressof(sol), watch.addr, T[0].data_ptr(), 0, None, 0, *one) == abi_error
    assert torch.all(out == 7.0)
    Tq = torch.zeros(4, 4, dtype=torch.float64)
    assert unchanged(watch.addr) == abi_error
    assert fk_one(ctypes.addressof(chain_args), watch.addr, q[0].data_ptr(), Tq.data_ptr(), None) == abi_error
    assert not Tq.any()

    A, ok = torch.zeros(1, 3, 4, dtype=torch.float64), torch.ones(4, dtype=torch.bool)
    r, w = torch.ones(1, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)  # alive for the calls
    # four unit capsules at the origin and a unit sphere there: every configuration in collision
    c = native.new_struct(native.Collide, real_bytes=8, N=4, G=1, P=0, Wr=1, H=0, nthreads=1, A=A, B=A, r=r,
                          wa=w, wb=w, wr=r, margin=0.0, slack=0.0, ok=ok.view(torch.uint8))
    assert lib.dk_collide_clear(ctypes.byref(c)) == 0 and not ok.any()  # the right struct: all in collision
    ok.fill_(True)
    setattr(c, wrong, off(native.Collide))
    assert lib.dk_collide_clear(ctypes.byref(c)) == abi_error and ok.all()  # refused: nothing cleared


@pytest.mark.parametrize("mismatch", ["fk version", "solve version", "constant"])
def test_a_mismatched_library_is_rebuilt_then_refused_with_one_warning(monkeypatch, tmp_path, mismatch):
    """native.py speaking another interface than the C file (the FK's struct, the solve's struct (a new
    solver option on one side only), a constant): the library is built, refused, built again once, refused;
    one warning, and the torch kernels serve the calls. The "compiler" copies this session's library (the
    check is what is tested, not the compiler)."""
    import shutil

    monkeypatch.setenv("DIFFKIN_CACHE_DIR", str(tmp_path))
    if mismatch == "fk version":
        v = native.Args.VERSION
        monkeypatch.setattr(native.Args, "VERSION", v + 1)
        said = f"args struct does not match Args: version {v} .library. vs {v + 1}"
    elif mismatch == "solve version":
        v = native.SolveArgs.VERSION
        monkeypatch.setattr(native.SolveArgs, "VERSION", v + 1)
        said = f"solve struct does not match SolveArgs: version {v} .library. vs {v + 1}"
    else:
        monkeypatch.setitem(native.CONSTANTS, "MAX_RANKS", 65)
        said = r"constants differ: MAX_RANKS 64 \(library\) vs 65"
    built = native._path
    monkeypatch.setattr(native, "_lib", None)
    monkeypatch.setattr(native, "_tried", False)
    monkeypatch.setattr(native, "_OPTIONAL", native._OPTIONAL[:1])
    compiles = []

    def stand_in(flags):
        compiles.append(flags)
        out = native.library_path(flags)
        shutil.copyfile(built, out)
        return out

    monkeypatch.setattr(native, "_compile", stand_in)
    with pytest.warns(RuntimeWarning, match=f"serve every call.*{said}"):
        assert not native.available()
    assert len(compiles) == 2  # the first load, then the one rebuild
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once
        assert not native.available()
        chain = models.load("panda", dtype=torch.float64)
        q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(12))
        with torch.no_grad():
            assert chain._native_model(q) is None
            assert torch.isfinite(chain.forward_kinematics(q)).all()


def test_a_copied_or_pickled_chain_keeps_its_native_constants():
    import copy
    import pickle

    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((20,), generator=torch.Generator().manual_seed(14))
    with torch.no_grad():
        T = chain.forward_kinematics(q)  # the packed constants now live on the chain's Segments
        packed = chain._native_model(q)
        for other in (copy.deepcopy(chain), pickle.loads(pickle.dumps(chain))):
            twin = other._native_model(q)
            assert twin is not None and twin.args[torch.float64].pre != packed.args[torch.float64].pre
            torch.testing.assert_close(other.forward_kinematics(q), T, atol=0, rtol=0)
        clone = copy.deepcopy(packed)  # its own arrays, its own addresses
        assert clone.args[torch.float64].mult == clone.reals[torch.float64]["mult"].data_ptr()
        assert torch.equal(native.fk_jacobian(clone, q, True)[1], native.fk_jacobian(packed, q, True)[1])
