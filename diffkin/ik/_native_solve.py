"""The whole :func:`diffkin.ik.solve` in one C call (private): ``dk_solve`` of ``kernels/_native_solve.c``.

It serves CPU solves without autograd on every chain the fused kernel takes (1-DOF joints, ball and free
joints: floating bases); CUDA, ``progress`` and other chains run the torch backend (:mod:`._lm`). Both run
one algorithm, the schedule of :mod:`._lm` (each target's seeds one after another, the LM step (3.59) with
the joint limits as q = c + h sin u on the scalar coordinates, steps of nv velocities integrated on the
manifold as :meth:`~diffkin.kernels.configuration.ConfigurationSpace.integrate` does: Q ⊗ exp(ω/2) on each
unit quaternion), from the seeds of :mod:`._seeds` (the user's, the fixed library's nearest poses, then the
pool drawn from the caller's generator): on the same inputs the same success flags, iterations and q to
rounding. The C solve fills W = 16 lanes with one target each, so its answers do not depend on the thread
count.

:func:`solve_one` is the lean front for one target: plain checks in Python, then one foreign call
(``dk_solve_one``: the cache check, the rigidity check and the solve; with ``seed=`` the random seeds drawn
in C from torch's CPU stream, only those used).
"""

from __future__ import annotations

import ctypes
import math
import threading

import torch
from torch import Tensor

from ..kernels import native, single
from ..kernels.cache import Data, filled
from . import _seeds
from ._kernel import JointMap
from ._lm import LMConfig
from .implicit import attach_solve_gradients
from .residuals import PoseResidual
from .result import IKResult, final_errors


class _Prepared:
    """A chain's fixed inputs of ``dk_solve`` for one (state, compute dtype, respect_limits, library size):
    the packed model, the joint map and its arrays, the limits of the final check and the fixed library."""

    def __init__(self, chain, packed: native.NativeModel, dtype: torch.dtype, respect_limits: bool, L: int):
        self.packed, self.dtype, self.n = packed, dtype, chain.n_joints
        self.nu = chain.configuration_space.n_uniform  # uniforms per random seed (3 per quaternion)
        jm = self.jmap = JointMap(chain, dtype, torch.device("cpu"), respect_limits)
        limited = respect_limits and chain.q_limits is not None
        if limited:
            lo, hi = (t.to(dtype).contiguous() for t in chain.q_limits.detach().unbind(-1))
        else:
            lo, hi = (torch.full((self.n,), v, dtype=dtype) for v in (-math.inf, math.inf))
        self.arrays = [jm.c.reshape(-1).contiguous(), jm.h.reshape(-1).contiguous(),
                       jm.bounded.reshape(-1).to(torch.uint8).contiguous(),
                       jm.rev.reshape(-1).to(torch.uint8).contiguous(), lo, hi]
        self.clamp = int(limited)
        self.lib_u = self.lib_pose = None
        if L > 0:
            u = _seeds.library_u(jm, L)
            T, _, _ = native.fk_jacobian(packed, jm.q_of_u(u).T.contiguous().to(dtype), threads=1)
            self.lib_u = u.T.contiguous()  # (L, n)
            # (12K, L): p, x, y, z of every end link (the layout of the targets' columns), feature-major
            # for the vectorised nearest-pose search
            self.lib_pose = T[:, :, :3, [3, 0, 1, 2]].permute(0, 3, 1, 2).reshape(L, -1).T.contiguous()
        self.L, self._configured, self._one = L, {}, {}
        # the two caches are filled once per key (C calls use their addresses); re-entrant: one() fills
        # configured()
        self._lock = threading.RLock()
        # solve_one's outputs by empty_like (half the cost of torch.empty with a dtype): q, a real, a flag,
        # a count
        self.outs = (torch.empty(self.n, dtype=dtype), torch.empty((), dtype=dtype),
                     torch.empty((), dtype=torch.bool), torch.empty((), dtype=torch.int64))
        self.chain = packed.args[dtype]  # the chain's dk_args (packed keeps it alive): its address below
        self.base = native.new_struct(native.SolveArgs, chain=ctypes.addressof(self.chain), jc=self.arrays[0],
                                      jh=self.arrays[1], bounded=self.arrays[2], wrap=self.arrays[3], qlo=lo,
                                      qhi=hi, clamp=self.clamp, n_lib=L, lib_u=self.lib_u,
                                      lib_pose=self.lib_pose)


    def configured(self, cfg: LMConfig, position_only: bool, K: int) -> native.SolveArgs:
        """:attr:`base` with the fields of ``cfg`` and the row weights set (cached per option set)."""
        def make():
            rot = [] if position_only else [math.sqrt(cfg.orientation_weight)] * 3
            sqrt_w = torch.tensor(([1.0] * 3 + rot) * K, dtype=self.dtype)
            return sqrt_w, native._filled(
                native.SolveArgs.from_buffer_copy(self.base), sqrt_w=sqrt_w, iters=cfg.check_every,
                damping2=cfg.damping, error_damping=cfg.error_damping, margin=cfg.margin,
                min_seed_iterations=cfg.min_seed_iterations, stall_ratio=cfg.stall_ratio,
                feature_weight=cfg.orientation_weight)

        return filled(self._configured, (cfg, position_only, K), self._lock, make)[1]

    def one(self, tol: tuple, num_seeds: int, max_iterations: int) -> tuple[int, int]:
        """The address of the filled ``dk_solve_args`` of a one-target call with default options (every
        field but the target, the pool and the outputs: ``dk_solve_one`` copies the struct and sets them),
        and the pool's length (cached per option set)."""
        def make():
            R = _seeds.ranks(self.L, 1, _DEFAULT.library_ranks)
            P = _seeds.pool_size(1, num_seeds, 0, R)
            args = native._filled(
                native.SolveArgs.from_buffer_copy(self.configured(_DEFAULT, False, 1)), n_targets=1,
                tol_p=tol[0], tol_o=tol[1], n_seeds=num_seeds, max_iterations=max_iterations, n_user=0,
                user_u=None, lib_ranks=R, n_pool=P, nthreads=1, target_stride=4)  # a row-major (4, 4) pose
            return ctypes.addressof(args), P * self.nu, args  # args keeps the address

        return filled(self._one, (tol, num_seeds, max_iterations), self._lock, make)[:2]


def _entry(chain, x: Tensor) -> Data | None:
    """The chain's current :class:`~diffkin.kernels.cache.Data` with its lean state
    (:func:`diffkin.kernels.single.entry`) when ``dk_solve`` can serve it: the fused kernel serves the chain
    (every joint kind: dk_solve steps scalars additively and quaternions on the manifold). None otherwise."""
    return single.entry(chain, x, grad=False)  # the iterations never need autograd (gradients: attached)


def prepared(chain, x: Tensor, dtype: torch.dtype, respect_limits: bool, L: int) -> _Prepared | None:
    """The :class:`_Prepared` of ``chain`` for these options, kept in the ``extra`` slot of its
    :class:`~diffkin.kernels.cache.Data` (dropped with it when a parameter or buffer changes); None when
    the fused kernel cannot serve it."""
    hit = _entry(chain, x)
    if hit is None:
        return None
    return hit.derived(("solve", dtype, respect_limits, L),
                       lambda: _Prepared(chain, hit.native, dtype, respect_limits, L))


def applies(chain, T_target: Tensor, progress: bool) -> bool:
    """Whether the C solve serves this call: CPU and a chain the fused kernel supports (the iterations run
    without autograd either way; gradients are attached at the solution afterwards). Asked first whether
    the library is in use: a chain's Data outlives :func:`~diffkin.kernels.native.disabled`."""
    if progress or T_target.device.type != "cpu" or chain.device.type != "cpu" or not native.available():
        return False
    return _entry(chain, T_target) is not None


def run(prep: _Prepared, cols: tuple, N: int, cfg: LMConfig, generator, *, tol, num_seeds: int,
        max_iterations: int, user_u: Tensor | None, threads: int | None = None, K: int = 1, outs=None,
        library: tuple[Tensor, Tensor] | None = None):
    """One ``dk_solve`` call: ``cols`` the targets' ``(pd, xd, yd, zd)`` columns ``(3K, N)`` (tensors or
    addresses; xd None: position only) in the compute dtype; ``user_u (N, S, n)`` the user's seeds in u;
    ``library``: ``(u (L, n), poses (12K, L))`` in the layout of :class:`_Prepared` instead of its fixed
    library (collision-free poses, :mod:`diffkin.ik._collision_native`).
    Returns ``outs`` (default new tensors): ``(q (N, n), success (N,), position error (N,), orientation
    error (N,), iterations (N,), seeds tried (N,))``, q and the errors in the compute dtype."""
    dtype, n = prep.dtype, prep.n
    S = 0 if user_u is None else user_u.shape[1]
    L = prep.L if library is None else library[0].shape[0]
    R = _seeds.ranks(L, K, cfg.library_ranks)
    P = _seeds.pool_size(N, num_seeds, S, R)
    pool = _seeds.draw_pool(generator, P, prep.nu, dtype)
    if outs is None:
        errs, counts = torch.empty(2, N, dtype=dtype), torch.empty(2, N, dtype=torch.int64)
        outs = (torch.empty(N, n, dtype=dtype), torch.empty(N, dtype=torch.bool), *errs, *counts)
    args = native._filled(
        native.SolveArgs.from_buffer_copy(prep.configured(cfg, cols[1] is None, K)),
        n_targets=N, pd=cols[0], xd=cols[1], yd=cols[2], zd=cols[3], tol_p=tol[0], tol_o=tol[1],
        n_seeds=num_seeds, max_iterations=max_iterations, n_user=S, user_u=user_u, lib_ranks=R, n_pool=P,
        pool=pool, q_out=outs[0], success=outs[1], pos_err=outs[2], ori_err=outs[3], iters_out=outs[4],
        seeds_out=outs[5], nthreads=threads or native.thread_count(64 * N))
    if library is not None:
        native._filled(args, n_lib=L, lib_u=library[0], lib_pose=library[1])
    native.solve_call(args)
    return outs


def solve_batch(chain, tg, batch, T_orig, seeds_user, cfg: LMConfig, generator, dtype, *, tol, num_seeds,
                max_iterations, respect_limits, position_only) -> IKResult | None:
    """:func:`diffkin.ik.solve` of validated targets through ``dk_solve`` (no gradients attached); None
    when it cannot serve."""
    with torch.no_grad():
        return _solve_batch(chain, tg, batch, T_orig, seeds_user, cfg, generator, dtype, tol=tol,
                            num_seeds=num_seeds, max_iterations=max_iterations, respect_limits=respect_limits,
                            position_only=position_only)


def _solve_batch(chain, tg, batch, T_orig, seeds_user, cfg: LMConfig, generator, dtype, *, tol, num_seeds,
                 max_iterations, respect_limits, position_only) -> IKResult | None:
    prep = prepared(chain, tg.pd, dtype, respect_limits, max(cfg.library_size, 0))
    if prep is None:
        return None
    N, n = math.prod(batch), chain.n_joints
    user_u = user_seeds(prep, seeds_user, num_seeds)
    out = run(prep, columns(tg), N, cfg, generator, tol=tol, num_seeds=num_seeds,
              max_iterations=max_iterations, user_u=user_u, K=chain.n_ends)
    q, ok, pe, oe = checked(chain, prep, out, T_orig.reshape(N, *T_orig.shape[len(batch):]), tol,
                            position_only)
    return IKResult(q=q.reshape(*batch, n), success=ok.reshape(batch), position_error=pe.reshape(batch),
                    orientation_error=oe.reshape(batch), iterations=out[4].reshape(batch),
                    seeds_tried=out[5].reshape(batch))


def user_seeds(prep: _Prepared, seeds_user: Tensor | None, num_seeds: int) -> Tensor | None:
    """The user's seeds ``(N, S, n)`` in q as :func:`run`'s ``user_u`` (at most ``num_seeds`` each)."""
    if seeds_user is None:
        return None
    N, n = seeds_user.shape[0], prep.n
    S = min(seeds_user.shape[1], max(num_seeds, 1))
    flat = seeds_user[:, :S].to(prep.dtype).reshape(-1, n).T
    return prep.jmap.u_of_q(flat).T.reshape(N, S, n).contiguous()


def columns(tg) -> tuple:
    """The targets' ``(pd, xd, yd, zd)`` columns of :func:`run` (contiguous; None: position only)."""
    return tuple(None if t is None else t.contiguous() for t in (tg.pd, tg.xd, tg.yd, tg.zd))


def checked(chain, prep: _Prepared, out, T: Tensor, tol, position_only: bool):
    """``(q (N, n), success, position error, orientation error)`` of :func:`run`'s ``out`` for the targets
    ``T (N, ...)`` in the chain's dtype: the final check redone there when the compute dtype differs (and
    the orientation error reported for pose targets of a position-only solve)."""
    q, ok, pe, oe = out[:4]
    q = q.to(chain.dtype)
    if prep.dtype != chain.dtype or (position_only and T.shape[-1] == 4):
        pe, oe = final_errors(chain, q, T, position_only)
        ok = pe <= tol[0]
        if not position_only:
            ok &= oe <= tol[1]
        if prep.clamp:
            ok &= chain.within_limits(q, check=False)
    return q, ok, pe.to(chain.dtype), oe.to(chain.dtype)


__all__ = ["applies", "solve_batch", "run", "prepared", "columns", "checked", "user_seeds"]


_DEFAULT = LMConfig()
_ONE = ("solve_one",)  # the Data.extra key of the default-options _Prepared a one-target call uses
_NOT_RIGID = native.CONSTANTS["DK_NOT_RIGID"]
_SEED_MAX = 2**63  # seeds from 0 below this: the pool drawn in C as torch.Generator().manual_seed(seed) draws
_typed: tuple = (None, None)  # (the loaded library, its dk_solve_one typed)


def _solve_one_fn():
    """``dk_solve_one`` of the loaded library, typed once per library (plain addresses and integers: no
    per-call type checks of ctypes pointers)."""
    global _typed
    lib = native._lib
    if _typed[0] is not lib:
        fn = lib.dk_solve_one
        fn.restype = ctypes.c_int64
        fn.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64] + \
            [ctypes.c_void_p] * 6
        _typed = (lib, fn)
    return _typed[1]


def solve_one(chain, T: Tensor, generator, seed, *, num_seeds, max_iterations, tol) -> IKResult | None:
    """The lean front of :func:`diffkin.ik.solve` for ONE target pose ``T (4, 4)`` with default options
    (no ``q0``, ``base``, ``config``, ``damping``, position-only or closed-form seeds): plain attribute
    checks, then one foreign call, ``dk_solve_one``, that checks the packed constants are still the chain's
    and the target is rigid, and solves (with ``seed=`` and no generator it draws the pool itself, the
    numbers ``torch.rand`` would draw from ``torch.Generator().manual_seed(seed)``, and only those the
    seeds use); then the implicit gradient attached when the target or a chain parameter requires grad (as
    the general path). None when it does not apply (the general path then serves the call, with its
    validation and errors)."""
    tp, to = tol
    # plain values only (bools, floats as counts, tensors: the general path's checks and errors)
    if type(T) is not Tensor or T.shape != (4, 4) or not T.is_cpu or not T.is_contiguous() \
            or type(num_seeds) is not int or num_seeds < 1 or type(max_iterations) is not int \
            or max_iterations < 1 or type(tp) not in (float, int) or not 0 < tp < math.inf \
            or type(to) not in (float, int) or not 0 < to < math.inf \
            or (generator is not None and generator.device.type != "cpu") \
            or (seed is not None and type(seed) is not int) or torch.compiler.is_compiling() \
            or single._is_wrapped(T) or not native.available() \
            or (T.dtype is torch.float32 and min(tol) < 1e-5) or not chain._single_end:
        return None
    state = _one_state(chain, T, tol, num_seeds, max_iterations)
    if state is None:
        return None
    watch, tmpl, npool, (tq, treal, tflag, tcount), _ = state  # the last keeps Data and pack alive
    empty = torch.empty_like
    q, ok, pe, oe, its, seeds = (empty(tq), empty(tflag), empty(treal), empty(treal), empty(tcount),
                                 empty(tcount))
    pool = None
    if generator is None and seed is not None and 0 <= seed < _SEED_MAX:
        stream = seed  # drawn in C, as needed
    else:  # the caller's generator (or torch's default one): the whole pool, as the general path draws it
        stream = -1
        if generator is None and seed is not None:
            generator = _seeded(seed)
        pool = torch.rand(npool, generator=generator, dtype=T.dtype) if npool else None  # alive for the call
    outputs = (q.data_ptr(), ok.data_ptr(), pe.data_ptr(), oe.data_ptr(), its.data_ptr(), seeds.data_ptr())
    call = lambda w, t: _solve_one_fn()(t, w, T.data_ptr(), stream,  # noqa: E731
                                        None if pool is None else pool.data_ptr(), npool, *outputs)
    status = call(watch, tmpl)
    if status == single._STALE:  # bytes written in place since the Data was made: repacked, the same pool
        single._remade(chain)
        state = _one_state(chain, T, tol, num_seeds, max_iterations)
        status = single._STALE if state is None else call(*state[:2])
    if status != 0:
        if status == _NOT_RIGID or status == single._STALE:  # the general path: its error, or a repack
            return None
        native._raise_on(status, "work space")
    if torch.is_grad_enabled() and _wants_gradients(chain, T):
        # as the general path: the implicit-function gradient at the solution
        q = attach_solve_gradients(chain, q, T, ok, PoseResidual(False, _DEFAULT.orientation_weight),
                                   _DEFAULT.damping)
    return IKResult(q=q, success=ok, position_error=pe, orientation_error=oe, iterations=its,
                    seeds_tried=seeds)


def _one_state(chain, T: Tensor, tol: tuple, num_seeds: int, max_iterations: int):
    """``(watch address, dk_solve_one's argument template address, pool length, output templates, (Data,
    pack))`` of the chain's Data for a one-target call (the pointers checked here; ``dk_solve_one``
    compares the bytes), or None where the fused kernel does not serve the chain in ``T``'s dtype. The
    caller holds the last item through the call: the addresses point into those objects, and another
    thread may replace the chain's Data meanwhile."""
    hit = single._current(chain, False)
    if hit is None or T.dtype is not hit.dtype:
        return None
    prep = hit.derived(_ONE, lambda: prepared(chain, T, T.dtype, True, _DEFAULT.library_size))
    if prep is None:
        return None
    tmpl, npool = prep.one(tol, num_seeds, max_iterations)
    return hit.watch_addr, tmpl, npool, prep.outs, (hit, prep)


def _wants_gradients(chain, T: Tensor) -> bool:
    """Whether the target or a chain parameter requires grad (a loop over the parameters: no module walk)."""
    if T.requires_grad:
        return True
    for p in chain.__dict__["_parameters"].values():
        if p is not None and p.requires_grad:
            return True
    return False


_local = threading.local()  # per thread: the generator solve_one seeds for a call with seed=


def _seeded(seed: int) -> torch.Generator:
    """This thread's CPU generator reseeded with ``seed``: the draws of
    ``torch.Generator().manual_seed(seed)`` at half its cost (used for one draw at once, never handed out)."""
    g = getattr(_local, "generator", None)
    if g is None:
        g = _local.generator = torch.Generator()
    return g.manual_seed(seed)
