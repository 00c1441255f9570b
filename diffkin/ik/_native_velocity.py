"""One differential-IK step in C: mink's ``solve_ik`` for frame tasks, a posture task, configuration and
velocity limits, on resolved numeric inputs (``_native_velocity.c``, one foreign call for one row or a
batch).

:class:`NativeVelocity` holds one problem's constants, packed once for one chain and dtype: which end links
carry a frame task and their costs, gains and Levenberg–Marquardt damping, the posture task's cost per
velocity (0 on a free joint's six, as mink), gain and damping, the configuration limits per velocity (lower
and upper, ``min_distance_from_limits`` folded in, and the gain), the velocity limits per velocity and
the QP's damping. :meth:`NativeVelocity.solve` runs a batch; :meth:`NativeVelocity.step` one row ``q (nq,)``
with no torch operation but its output's allocation (none when ``out=`` is given): the chain's packed
constants come from the chain's :class:`~diffkin.kernels.cache.Data` (checked on every call by its one
rule, the bytes in C), the QP's work space stays between calls. :func:`route` keeps its problems in that
Data too, so a change of the chain's limits or masses makes new ones.

The QP, per row (mink's ``build_ik``; Δq the step, v = Δq / dt)::

    min ½ Δqᵀ H Δq + cᵀ Δq  s.t.  lo ≤ Δq ≤ hi
    H = damping·I + Σ (AᵀA + μ I),  c = −Σ Aᵀ b,  A = C J,  b = −gain · C e,  μ = lm_damping · ‖b‖²

with e, J of a frame task log(T_b⁻¹ T_t) and −jlog(T_t⁻¹ T_b) J_body, of the posture task q ⊖ q_ref and I;
lo, hi the intersection of gain·(q_min − q) ≤ Δq ≤ gain·(q_max − q) and |Δq| ≤ dt·v_max. Solved exactly
(active set on Cholesky factors), not approximately: the answer is the QP's minimiser to rounding.

Version 3 of ``dk_vel`` adds a ComTask (e = p_C − target, J = J_C, computed in C from the FK block's frames
and the chain's link masses) and a CollisionLimit: rows −J_d Δq ≤ γ max(d − d_min, 0) for every checked
distance d < d_detect (capsule self pairs, capsules against world spheres, capsules, points and half-spaces),
the QP with them solved exactly (a dual active set, after the box QP whose minimiser is kept where it meets
every row).
"""

from __future__ import annotations

import ctypes
import math
import struct
import threading
from collections.abc import Sequence

import torch
from torch import Tensor

from .._numerics import tol_for
from ..kernels import cache, native, single

__all__ = ["NativeVelocity", "VERSION", "Vel", "available", "route"]

#: the version of dk_vel this module speaks (DK_VEL_VERSION in _native_velocity.c)
VERSION = 3
_I64, _F64, _PTR = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
_STALE = native.CONSTANTS["DK_STALE"]
_LEAN = cache.KEY  # the chain's Data in its instance __dict__
_pack = struct.Struct("=5Qd").pack  # dk_velocity_step's call block: q, target, q_ref, v, q_next, dt


# v3: the ComTask (the bodies' centres and weights, cost, gain, damping, the target) and the CollisionLimit
# (capsules on frames, self pairs, round world objects and half-spaces, gain, minimum and detection distance)
_V3_FIELDS = [("n_bodies", _I64)] + \
    [(name, _PTR) for name in ("body_frame", "body_point", "body_weight", "com_cost")] + \
    [("com_gain", _F64), ("com_lm", _F64), ("com_target", _PTR), ("com_stride", _I64), ("n_caps", _I64)] + \
    [(name, _PTR) for name in ("cap_frame", "cap_a", "cap_b", "cap_r", "cap_moving")] + \
    [("n_pairs", _I64), ("pair_i", _PTR), ("pair_j", _PTR), ("n_round", _I64), ("round_a", _PTR),
     ("round_b", _PTR), ("round_r", _PTR), ("n_half", _I64), ("half", _PTR), ("coll_gain", _F64),
     ("coll_min", _F64), ("coll_detect", _F64)]


class Vel(ctypes.Structure):
    """``dk_vel`` of ``_native_velocity.c`` (``DK_VEL_FIELDS``, where each field is described)."""

    VERSION = VERSION
    _fields_ = [(name, _I64) for name in ("version", "size", "nthreads", "batch", "n_frames")] + \
        [(name, _PTR) for name in ("frame_end", "frame_cost", "frame_gain", "frame_lm", "target")] + \
        [("target_stride", _I64), ("posture_cost", _PTR), ("posture_gain", _F64), ("posture_lm", _F64),
         ("q_ref", _PTR), ("ref_stride", _I64), ("pos_lo", _PTR), ("pos_hi", _PTR), ("limit_gain", _F64),
         ("vmax", _PTR), ("dt", _F64), ("damping", _F64)] + \
        [(name, _PTR) for name in ("q", "v", "q_next", "ok", "work")] + [("ready", _I64), ("busy", _I64)] + \
        _V3_FIELDS


_fns: dict = {}  # id of the loaded library -> (dk_velocity_step, dk_velocity_work_bytes, dk_velocity)


def _functions():
    """The loaded library's entry points, its ``dk_vel`` checked against :class:`Vel` once (a mismatch:
    :class:`~diffkin.kernels.native.AbiMismatch`)."""
    lib = native._lib
    fns = _fns.get(id(lib))
    if fns is None:
        native.check_layout(lib, "vel", Vel)
        one = ctypes.PyDLL(native._path).dk_velocity_step  # keeps the GIL: the call takes microseconds
        one.restype, one.argtypes = _I64, [_PTR, ctypes.c_char_p]  # two arguments to convert, not nine
        batch = lib.dk_velocity  # releases the GIL (threads, milliseconds)
        batch.restype, batch.argtypes = _I64, [_PTR, _PTR, _PTR]
        size = lib.dk_velocity_work_bytes
        size.restype, size.argtypes = _I64, [_PTR]
        fns = _fns[id(lib)] = (one, size, batch)
    return fns


def available() -> bool:
    """True when the fused library is loaded with ``dk_velocity`` (built on first use)."""
    if not native.available():
        return False
    try:
        _functions()
    except (AttributeError, native.AbiMismatch):
        return False
    return True


def _free_velocities(chain) -> list[int]:
    """The velocities of the chain's free joints (mink's posture task leaves them out)."""
    kinds = getattr(chain, "joint_kinds", None)
    if not kinds:
        return []
    from ..kernels.configuration import joint_kind

    out, v = [], 0
    for kind in kinds:
        nv = joint_kind(kind).nv
        if kind == "free":
            out.extend(range(v, v + nv))
        v += nv
    return out if v == chain.nv else []


class NativeVelocity:
    """One differential-IK problem's constants for the C step (see the module doc).

    ``frames``: per frame task ``(end, position_cost, orientation_cost, gain, lm_damping)``, ``end`` an index
    into the chain's end links, costs numbers or ``(3,)``; ``posture``: ``(cost, gain, lm_damping)`` with
    ``cost`` a number or ``(nv,)``, or None; ``configuration_limit``: ``(gain, min_distance_from_limits)``
    or None (the chain's ``q_limits``); ``velocity_limit``: a number or ``(nv,)`` (inf: none) or None;
    ``damping``: added to H's diagonal (mink's ``damping``). v3: ``com``: ``(cost, gain, lm_damping)`` of a
    ComTask (cost a number or ``(3,)``; its target is given per call: ``com_target=`` of :meth:`solve` /
    :meth:`step`) or None; ``collision``: ``(collision, world, gain, minimum_distance,
    detection_distance)`` of a CollisionLimit (:func:`_pack_collision`) or None.
    """

    def __init__(self, chain, frames: Sequence[tuple], *, posture=None, configuration_limit=None,
                 velocity_limit=None, damping: float = 1e-12, dtype: torch.dtype | None = None,
                 com=None, collision=None):
        self.chain = chain
        self.dtype = dtype = dtype or chain.dtype
        nv, K = chain.nv, chain.n_ends
        self.nq, self.nv = chain.nq, nv
        kw = dict(dtype=dtype)
        self.n_frames = len(frames)
        ends, cost, gain, lm = [], [], [], []
        for end, pc, oc, g, d in frames:
            if not 0 <= int(end) < K:
                raise ValueError(f"frame task end {end} is not an end link index in [0, {K})")
            ends.append(int(end))
            cost.append(torch.cat([torch.as_tensor(pc, **kw).expand(3), torch.as_tensor(oc, **kw).expand(3)]))
            gain.append(float(g))
            lm.append(float(d))
        self._frame_end = torch.tensor(ends or [0], dtype=torch.int32)
        self._frame_cost = torch.stack(cost) if cost else torch.zeros(1, 6, **kw)
        self._frame_gain = torch.tensor(gain or [0.0], **kw)
        self._frame_lm = torch.tensor(lm or [0.0], **kw)
        self._posture = None
        if posture is not None:
            pcost, pgain, plm = posture
            c = torch.as_tensor(pcost, **kw).expand(nv).clone()
            c[_free_velocities(chain)] = 0.0
            self._posture = (c.contiguous(), float(pgain), float(plm))
        self._limits = None
        if configuration_limit is not None and chain.q_limits is not None:
            lgain, md = configuration_limit
            vq = _velocity_coordinates(chain)
            lim = chain.q_limits.detach().to("cpu", dtype)
            lo, hi = torch.full((nv,), -math.inf, **kw), torch.full((nv,), math.inf, **kw)
            for v, i in enumerate(vq):
                if i >= 0 and math.isfinite(lim[i, 0]) and math.isfinite(lim[i, 1]):
                    lo[v], hi[v] = lim[i, 0] + md, lim[i, 1] - md
            self._limits = (lo, hi, float(lgain))
        self._vmax = None
        if velocity_limit is not None:
            self._vmax = torch.as_tensor(velocity_limit, **kw).expand(nv).contiguous().clone()
        self.damping = float(damping)
        self._rows = _pack_rows(chain, dtype, com, collision)  # v3: ComTask, CollisionLimit (or None)
        self._args = self._filled()
        _fill_rows(self._args, self._rows)
        self._entry = None  # the lean path's state: (the chain's Data, dk_velocity_step, ...: see _lean)
        self._cdict = chain.__dict__  # where the chain keeps its Data
        self.owned = False  # True: kept in a Data's extra by route (its limits and masses are that Data's)
        self._v = torch.empty(nv, dtype=dtype)  # step's output template
        self._ok = ctypes.c_uint8(1)
        self._com_lock = threading.Lock()  # step's ComTask target: one call's at a time

    @property
    def ok(self) -> bool:
        """Whether the last :meth:`step` found a feasible box and solved its QP."""
        return bool(self._ok.value)

    def _filled(self) -> Vel:
        p, lim = self._posture, self._limits
        a = Vel(version=VERSION, size=ctypes.sizeof(Vel), nthreads=1, n_frames=self.n_frames,
                frame_end=self._frame_end.data_ptr(), frame_cost=self._frame_cost.data_ptr(),
                frame_gain=self._frame_gain.data_ptr(), frame_lm=self._frame_lm.data_ptr(),
                damping=self.damping)
        if p is not None:
            a.posture_cost, a.posture_gain, a.posture_lm = p[0].data_ptr(), p[1], p[2]
        if lim is not None:
            a.pos_lo, a.pos_hi, a.limit_gain = lim[0].data_ptr(), lim[1].data_ptr(), lim[2]
        if self._vmax is not None:
            a.vmax = self._vmax.data_ptr()
        return a

    def _model(self):
        packed = self.chain._native_model(torch.empty(0, dtype=self.dtype))
        if packed is None:
            raise RuntimeError("the fused C kernel cannot serve this chain now (CUDA, gradients wanted, "
                               "or no C compiler)")
        return packed

    def solve(self, q: Tensor, targets: Tensor | None, q_ref: Tensor | None, dt: float, *,
              next_q: bool = False, threads: int | None = None, com_target: Tensor | None = None):
        """``q (B, nq)``, ``targets (B, F, 4, 4)`` or ``(F, 4, 4)`` (shared), ``q_ref (B, nq)`` or ``(nq,)``
        -> ``(v (B, nv), ok (B,) bool)``, or ``(v, q_next (B, nq), ok)`` with ``next_q``: CPU tensors of
        this problem's dtype (contiguous copies are made where needed)."""
        dtype, B = self.dtype, q.shape[0]
        q = q.detach().to(dtype).contiguous()
        tgt, tstride = self._targets(targets, B)
        ref, rstride = self._ref(q_ref, B)
        v = torch.empty(B, self.chain.nv, dtype=dtype)
        qn = torch.empty(B, self.chain.nq, dtype=dtype) if next_q else None
        ok = torch.empty(B, dtype=torch.bool)
        model = self._model()
        a = Vel.from_buffer_copy(self._args)
        a.nthreads = threads or native.thread_count(B)
        a.batch, a.target, a.target_stride, a.q_ref, a.ref_stride = B, tgt.data_ptr(), tstride, \
            (ref.data_ptr() if ref is not None else None), rstride
        a.dt, a.q, a.v, a.ok = float(dt), q.data_ptr(), v.data_ptr(), ok.data_ptr()
        a.q_next = qn.data_ptr() if qn is not None else None
        ct = self._com_target(com_target, B)
        if ct is not None:
            a.com_target, a.com_stride = ct[0].data_ptr(), ct[1]
        base = model.args[dtype]
        status = _functions()[2](ctypes.addressof(base), ctypes.addressof(a), None)
        _check(status)
        return (v, qn, ok) if next_q else (v, ok)

    def _targets(self, targets, B: int) -> tuple[Tensor, int]:
        F = self.n_frames
        if F == 0:
            return torch.zeros(16, dtype=self.dtype), 0
        t = targets.detach().to(self.dtype).contiguous()
        if t.shape == (F, 4, 4):
            return t, 0
        if t.shape != (B, F, 4, 4):
            raise ValueError(f"expected targets as ({F}, 4, 4) or ({B}, {F}, 4, 4), got {tuple(t.shape)}")
        return t, F * 16

    def _com_target(self, com_target, B: int) -> tuple[Tensor, int] | None:
        """The ComTask's target as ``(tensor, stride)``: ``(3,)`` shared or ``(B, 3)`` (None: no ComTask)."""
        if self._rows is None or "com_cost" not in self._rows:
            return None
        if com_target is None:
            raise ValueError("this problem has a ComTask: com_target (3,) or (B, 3) is needed")
        t = com_target.detach().to(self.dtype).contiguous()
        if t.shape == (3,):
            return t, 0
        if t.shape != (B, 3):
            raise ValueError(f"expected com_target as (3,) or ({B}, 3), got {tuple(t.shape)}")
        return t, 3

    def _ref(self, q_ref, B: int) -> tuple[Tensor | None, int]:
        if self._posture is None:
            return None, 0
        r = q_ref.detach().to(self.dtype).contiguous()
        nq = self.chain.nq
        if r.shape == (nq,):
            return r, 0
        if r.shape != (B, nq):
            raise ValueError(f"expected q_ref as ({nq},) or ({B}, {nq}), got {tuple(r.shape)}")
        return r, nq

    # ------------------------------------------------------------------------------- the lean path
    def _lean(self):
        """The chain's current Data and this problem's call struct bound to it (None: not servable:
        gradients wanted, CUDA, no library): ``(entry, dk_velocity_step, address of its fixed block, work
        space, the call's Vel, the fixed block)``."""
        chain = self.chain
        self._cdict = chain.__dict__
        hit = single._current(chain, torch.is_grad_enabled())
        if hit is None or hit.dtype is not self.dtype or hit.watch is None:
            return None
        if self._entry is None or self._entry[0] is not hit:
            step, size, _ = _functions()
            work = torch.zeros(max(int(size(hit.base)), 64) + 64, dtype=torch.uint8)
            a = Vel.from_buffer_copy(self._args)
            a.batch, a.nthreads = 1, 1
            a.work, a.ready = work.data_ptr() + (-work.data_ptr()) % 64, 0
            a.ok = ctypes.addressof(self._ok)
            fixed = (_PTR * 3)(hit.base, ctypes.addressof(a), hit.watch_addr)  # dk_args, dk_vel, dk_watch
            self._entry = (hit, step, ctypes.addressof(fixed), work, a, fixed)
        return self._entry

    def step(self, q: Tensor, targets: Tensor | None, q_ref: Tensor | None, dt: float, *,
             out: Tensor | None = None, next_q: Tensor | None = None,
             com_target: Tensor | None = None) -> Tensor | None:
        """One row: ``q (nq,)``, ``targets (F, 4, 4)``, ``q_ref (nq,)`` (contiguous CPU tensors of the
        problem's dtype, no gradient wanted) -> ``v (nv,)`` (into ``out`` when given; ``next_q (nq,)``
        receives q ⊕ Δq when given). None when this path cannot serve the call (the caller's general path
        then does) or q, a target or q_ref is not finite. :attr:`ok` says whether the box was feasible and
        the QP solved. ``com_target (3,)``: the ComTask's target, when the problem has one.

        A handful of Python operations around one foreign call (``dk_velocity_step``, two arguments): the
        entry is this problem's while the chain's Data is the one it was bound to (the chain's bytes
        are compared in C on every call)."""
        lean = self._entry
        if lean is None or lean[0] is not self._cdict.get(_LEAN) or q.dtype is not self.dtype or \
                not q.is_contiguous() or q.requires_grad:
            if not (q.dtype is self.dtype and q.is_contiguous() and not q.requires_grad):
                return None
            lean = self._lean()
            if lean is None:
                return None
        com = self._rows is not None and "com_cost" in self._rows  # v3: the ComTask's target (3,)
        if com and not (type(com_target) is Tensor and com_target.shape == (3,) and
                        com_target.dtype is self.dtype and com_target.is_contiguous() and com_target.is_cpu):
            return None
        v = torch.empty_like(self._v) if out is None else out  # empty_like: half torch.empty's cost
        packed = _pack(q.data_ptr(), 0 if targets is None else targets.data_ptr(),
                       0 if q_ref is None else q_ref.data_ptr(), v.data_ptr(),
                       0 if next_q is None else next_q.data_ptr(), dt)
        # the call struct is the problem's, shared by threads: the target is this call's until it returns
        if com:
            with self._com_lock:
                lean[4].com_target = com_target.data_ptr()
                status = lean[1](lean[2], packed)
        else:
            status = lean[1](lean[2], packed)
        if status == 0:
            return v
        if status == _STALE:  # the chain's bytes changed since they were packed: repacked once
            single._remade(self.chain)
            self._entry = None
            if self.owned or self._lean() is None:  # route's problems read the old Data: the torch path
                return None
            return self.step(q, targets, q_ref, dt, out=out, next_q=next_q, com_target=com_target)
        return None


# ----------------------------------------------------------------------- v3: ComTask and CollisionLimit rows
def _pack_rows(chain, dtype, com, collision) -> dict | None:
    """The arrays of the ComTask and the CollisionLimit for ``dk_vel`` (None: neither).

    ``com``: ``(cost, gain, lm_damping)``, cost a number or ``(3,)``: the bodies of
    :mod:`diffkin.center_of_mass` (``link_masses``, the centres ``link_inertial_frames[:, :3, 3]`` in the
    frames ``chain._mass_frames``, weights m_i / M). ``collision``: ``(collision, world, gain,
    minimum_distance, detection_distance)`` (a :class:`~diffkin.collision.RobotCollision` of capsules and a
    :class:`~diffkin.collision.World` of spheres, capsules, half-spaces and points without batch dims, or
    None): :func:`_pack_collision`. Raises ValueError where the C step does not serve them."""
    if com is None and collision is None:
        return None
    out: dict = {}
    kw = dict(dtype=dtype)
    if com is not None:
        cost, gain, lm = com
        m = getattr(chain, "link_masses", None)
        if m is None:
            raise ValueError("ComTask: the chain has no link masses")
        m = m.detach().to("cpu", torch.float64)
        out["body_frame"] = torch.tensor(list(chain._mass_frames), dtype=torch.int32)
        out["body_point"] = chain.link_inertial_frames.detach()[:, :3, 3].to("cpu", dtype).contiguous()
        out["body_weight"] = (m / m.sum()).to(dtype).contiguous()
        out["com_cost"] = torch.as_tensor(cost, **kw).expand(3).contiguous().clone()
        out["com_gain"], out["com_lm"] = float(gain), float(lm)
    if collision is not None:
        out.update(_pack_collision(chain, dtype, *collision))
    return out


def _fill_rows(a: Vel, rows: dict | None) -> None:
    """Set the v3 fields of ``a`` from :func:`_pack_rows`'s arrays (kept alive by the caller)."""
    if rows is None:
        return
    for name, value in rows.items():
        setattr(a, name, value.data_ptr() if isinstance(value, Tensor) else value)
    if "body_frame" in rows:
        a.n_bodies = rows["body_frame"].numel()
    if "cap_frame" in rows:
        a.n_caps, a.n_pairs = rows["cap_frame"].numel(), rows["pair_i"].numel()
        a.n_round, a.n_half = rows["round_r"].numel(), rows["half"].shape[0]


def _joint_frames(chain, q: Tensor) -> Tensor:
    """``(B, J + 1, 4, 4)``: the base and every joint frame F_j of the packed model (the frames the C step
    reads), from one fused FK call with every frame as an end link (as collision/_poses.py does)."""
    import dataclasses

    from ..kernels.tree import Segments

    seg, stacked = chain._constants()
    topo = dataclasses.replace(chain.topology, ends=tuple(range(chain.topology.n_frames)))
    ends = [None] * topo.n_frames
    model = native.NativeModel(topo, Segments(seg.pre, seg.offset, seg.post, seg.base, ends))
    T, _, bad = native.fk_jacobian(model, q.contiguous(), threads=1)
    if bad:
        raise ValueError("non-finite configuration")
    B = torch.eye(4, dtype=q.dtype) if stacked.base is None else stacked.base.detach().to(q.dtype)
    return torch.cat((B.expand(T.shape[0], 1, 4, 4), T), 1)


def _pack_collision(chain, dtype, collision, world, gain, minimum_distance, detection_distance) -> dict:
    """The CollisionLimit's arrays: each capsule's frame of the packed model and its ends there, found by
    matching the geom's pose (the collision model's own frames and offsets) to the joint frame it moves with
    rigidly, over three random configurations; the self pairs (not both fixed to the base); the world's
    spheres, capsules and points as segments with a radius, its half-spaces. ValueError where the C step
    does not serve the model (boxes, a batched world, a geom matched to no frame)."""
    if getattr(collision, "chain", None) is not chain:
        raise ValueError("CollisionLimit: the collision model is not on this chain")
    nc, nb = collision._counts
    if nb:
        raise ValueError("box geoms: the torch path")
    kw = dict(dtype=dtype)
    with torch.no_grad():
        g = torch.Generator().manual_seed(0)
        qs = chain.random_configuration(3, generator=g).detach().to(dtype)
        F = _joint_frames(chain, qs)  # (3, J + 1, 4, 4)
        Fr = collision._frames.frames(chain, qs)
        O = collision._frames.offsets(chain, dtype, "cpu")
        anchor, link = collision._col_anchor[:nc], collision._col_link[:nc]
        pose = Fr.index_select(1, anchor) @ O.index_select(0, link)  # (3, G, 4, 4)
        X = torch.linalg.solve(F.unsqueeze(2), pose.unsqueeze(1))  # (3, J + 1, G, 4, 4): F_f^-1 pose_g
        spread = (X - X[:1]).abs().amax((0, -2, -1))  # (J + 1, G)
        tol = tol_for(dtype, 1e-9, 1e-4)
        frames, a_loc, b_loc = [], [], []
        for gi in range(nc):
            hits = (spread[:, gi] <= tol).nonzero().flatten().tolist()
            if not hits:
                raise ValueError(f"geom {gi}: moves with no frame of the chain")
            f = hits[-1]  # the deepest frame it moves with
            Xg = X[0, f, gi]
            frames.append(f - 1)
            a_loc.append(Xg[:3, :3] @ collision.capsule_a[gi].detach().to(dtype) + Xg[:3, 3])
            b_loc.append(Xg[:3, :3] @ collision.capsule_b[gi].detach().to(dtype) + Xg[:3, 3])
    fixed = [f < 0 for f in frames]
    index = {geom.name: i for i, geom in enumerate(collision.geoms)}
    pairs = [(index[a], index[b]) for a, b in collision.pairs]
    pairs = [(i, j) for i, j in pairs if not (fixed[i] and fixed[j])]
    out = {"cap_frame": torch.tensor(frames, dtype=torch.int32),
           "cap_a": torch.stack(a_loc).contiguous() if nc else torch.zeros(1, 3, **kw),
           "cap_b": torch.stack(b_loc).contiguous() if nc else torch.zeros(1, 3, **kw),
           "cap_r": collision.capsule_radius.detach().to("cpu", dtype).contiguous(),
           "cap_moving": torch.tensor([not f for f in fixed] or [0], dtype=torch.uint8),
           "pair_i": torch.tensor([i for i, _ in pairs] or [0], dtype=torch.int32)[:len(pairs)].contiguous(),
           "pair_j": torch.tensor([j for _, j in pairs] or [0], dtype=torch.int32)[:len(pairs)].contiguous(),
           "coll_gain": float(gain), "coll_min": float(minimum_distance),
           "coll_detect": float(detection_distance)}
    ra, rb, rr, half = [], [], [], torch.zeros(0, 4, **kw)
    if world is not None:
        if world.boxes.center.shape[0] or any(t.ndim != 2 for t in (world.spheres, world.capsules,
                                                                        world.halfspaces, world.points)):
            raise ValueError("world boxes or a batched world: the torch path")
        sp, cp, pt = (t.detach().to("cpu", dtype) for t in (world.spheres, world.capsules, world.points))
        ra += [sp[:, :3], cp[:, :3], pt]
        rb += [sp[:, :3], cp[:, 3:6], pt]
        rr += [sp[:, 3], cp[:, 6], torch.zeros(pt.shape[0], **kw)]
        half = world.halfspaces.detach().to("cpu", dtype)
    out["round_a"] = torch.cat(ra).contiguous() if ra else torch.zeros(0, 3, **kw)
    out["round_b"] = torch.cat(rb).contiguous() if rb else torch.zeros(0, 3, **kw)
    out["round_r"] = torch.cat(rr).contiguous() if rr else torch.zeros(0, **kw)
    out["half"] = half.contiguous()
    return out


def _velocity_coordinates(chain) -> list[int]:
    """Per velocity the coordinate of q it moves (scalars), -1 inside a quaternion."""
    cs = chain.configuration_space
    out = [-1] * chain.nv
    for i, v in zip(cs.scalar_index("q"), cs.scalar_index("v")):
        out[v] = i
    return out


def _check(status: int) -> None:
    if status == -2:
        raise native.AbiMismatch("the native kernel refused the call's dk_args / dk_vel (another version "
                                 "or size)")
    if status == -1:
        raise MemoryError("the native kernel could not allocate its work space")


# ----------------------------------------------------------------------------------- solve_velocity's route
_CACHE = "velocity"  # in the chain's Data.extra: problem key -> NativeVelocity


def _number(x) -> float | None:
    return float(x) if type(x) in (float, int) else None


def _constant(x, n: int | None) -> tuple | float | None:
    """A cost / limit as a hashable constant: a number, or a short 1-D CPU tensor / sequence without
    gradient (its values); None when it is anything else (a batch of them, a gradient wanted)."""
    v = _number(x)
    if v is not None:
        return v
    if isinstance(x, Tensor):
        if x.ndim != 1 or x.requires_grad or not x.is_cpu or (n is not None and x.numel() != n):
            return None
        return tuple(x.tolist())
    if isinstance(x, list | tuple) and all(type(e) in (float, int) for e in x) and \
            (n is None or len(x) == n):
        return tuple(float(e) for e in x)
    return None


def _plain(t, tail: tuple, dtype) -> bool:
    return type(t) is Tensor and t.dtype is dtype and t.is_cpu and t.ndim >= len(tail) and \
        t.shape[t.ndim - len(tail):] == tail and not (t.requires_grad and torch.is_grad_enabled())


_NUM = (float, int)
_kinds: list = []  # (FrameTask, PostureTask, ConfigurationLimit, VelocityLimit, Problem), imported once


def _classes():
    if not _kinds:
        from .limits import ConfigurationLimit, VelocityLimit
        from .tasks import FrameTask, PostureTask, Problem

        _kinds.extend((FrameTask, PostureTask, ConfigurationLimit, VelocityLimit, Problem))
    return _kinds


_kinds3: list = []  # (ComTask, CollisionLimit), imported once (v3)


def _classes3():
    if not _kinds3:
        from .limits import CollisionLimit
        from .tasks import ComTask

        _kinds3.extend((ComTask, CollisionLimit))
    return _kinds3


def _collision_key(chain, lim, dtype) -> tuple | None:
    """A CollisionLimit as a hashable constant: the collision model (identity, its parameters' versions and
    storage), the world's tensors (the same), gain and distances; None where the C step does not serve it
    (another chain, box geoms, a world with boxes, cylinders, objects of registered kinds or batch dims,
    another dtype or device)."""
    rc, world = lim.collision, lim.world
    if getattr(rc, "chain", None) is not chain or getattr(rc, "_counts", (0, 1))[1] \
            or getattr(rc, "_nconvex", 0):  # (the C step holds capsules only)
        return None
    params = tuple(rc.parameters())
    if any(p.dtype is not dtype or not p.is_cpu for p in params):
        return None
    wkey = None
    if world is not None:
        ts = (world.spheres, world.capsules, world.halfspaces, world.points, world.boxes.center)
        if ts[4].shape[0] or any(t.ndim != 2 or t.dtype is not dtype or not t.is_cpu or
                                 (t.requires_grad and torch.is_grad_enabled()) for t in ts[:4]):
            return None
        if world.cylinders.shape[-2] or world.objects:  # the C step packs round objects and half-spaces only
            return None
        wkey = (id(world), *((id(t), t._version, t.data_ptr()) for t in ts))
    return (id(rc), tuple((p._version, p.data_ptr()) for p in params), wkey, lim.gain, lim.minimum_distance,
            lim.detection_distance)


def route(chain, q, tasks, dt, limits, damping) -> Tensor | None:
    """:func:`~diffkin.ik.solve_velocity` by the C step where it serves the call, else None (the torch
    path then serves it, and raises on bad input). Served: CPU tensors of the chain's dtype (float64 or
    float32), no gradient wanted (q, targets, q_ref, the chain's parameters), q ``(nq,)`` or ``(..., nq)``;
    tasks: FrameTask with a ``target`` pose (not ``twist``; frame by name or index; costs a number or
    ``(3,)``, gain and lm_damping numbers; the target ``(4, 4)`` or with q's batch dims), at most one
    PostureTask (cost a number or ``(nv,)``, q_ref ``(nq,)`` or with q's batch dims); limits:
    ConfigurationLimit and VelocityLimit (a number, ``(nv,)`` or a dict by joint name), at most one of each;
    ``dt`` and ``damping`` numbers. Also (v3) at most one ComTask (target ``(3,)`` or with q's batch dims,
    cost a number or ``(3,)``; a chain with link masses) and at most one CollisionLimit (a collision model of
    capsules on this chain, in its dtype, and a world of spheres, capsules, half-spaces and points without
    batch dims, or none). Everything else (box geoms or world boxes, a batched world, RelativeFrameTask,
    DampingTask, twists, batched costs, autograd, CUDA) takes the torch path.

    The problem's constants are packed once per chain and key (the tasks' frames, costs, gains and damping,
    the limits' constants, the chain's q_limits tensor and version) into a :class:`NativeVelocity`; a call
    then checks types and shapes, builds the key and makes one foreign call."""
    if type(q) is not Tensor:
        return None
    dtype = q.dtype
    if (dtype is not torch.float64 and dtype is not torch.float32) or not q.is_cpu or q.ndim == 0 or \
            (q.requires_grad and torch.is_grad_enabled()) or type(dt) not in _NUM or \
            type(damping) not in _NUM or not dt > 0 or not damping >= 0 or dt == math.inf:
        return None
    if native._disabled or (native._lib is None and not native.available()):
        return None
    FrameTask, PostureTask, ConfigurationLimit, VelocityLimit, Problem = _kinds or _classes()
    tasks = tasks if type(tasks) in (list, tuple) else (tasks,)
    limits = () if limits is None else limits if type(limits) in (list, tuple) else (limits,)
    ComTask, CollisionLimit = _kinds3 or _classes3()
    frames, targets, posture, q_ref = [], [], None, None
    com = com_target = coll = coll_key = None
    for t in tasks:
        kind = type(t)
        if kind is ComTask and com is None:
            c = t.cost
            com = (c if type(c) in _NUM else _constant(c, 3), _number(t.gain), _number(t.lm_damping))
            com_target = t.target
            if None in com or not _plain(com_target, (3,), dtype):
                return None
            continue
        if kind is FrameTask:
            if t.twist is not None or not _plain(t.target, (4, 4), dtype):
                return None
            pc, oc = t.position_cost, t.orientation_cost
            key = (t.frame, pc if type(pc) in _NUM else _constant(pc, 3),
                   oc if type(oc) in _NUM else _constant(oc, 3), _number(t.gain), _number(t.lm_damping))
            if None in key:
                return None
            frames.append(key)
            targets.append(t.target)
        elif kind is PostureTask and posture is None:
            c = t.cost
            posture = (c if type(c) in _NUM else _constant(c, None), _number(t.gain), _number(t.lm_damping))
            q_ref = t.q_ref
            if None in posture or type(q_ref) is not Tensor or q_ref.dtype is not dtype or \
                    (q_ref.requires_grad and torch.is_grad_enabled()):
                return None
        else:
            return None
    config = vel = None
    for lim in limits:
        kind = type(lim)
        if kind is ConfigurationLimit and config is None:
            config = (lim.gain, lim.min_distance_from_limits)
        elif kind is CollisionLimit and coll is None:
            coll, coll_key = lim, _collision_key(chain, lim, dtype)
            if coll_key is None:
                return None
        elif kind is VelocityLimit and vel is None:
            v = lim.velocity
            vel = v if type(v) in _NUM else _constant(v, None) if not isinstance(v, dict) else \
                ("dict", tuple((k, _constant(x, None)) for k, x in v.items()))
            if vel is None or (type(vel) is tuple and vel and vel[0] == "dict" and
                               any(x is None for _, x in vel[1])):
                return None
        else:
            return None
    if not frames and posture is None and com is None:
        return None
    # the problems read the chain's limits, masses and frames: kept on its Data (the one rule of
    # kernels/cache.py), dropped with it when a parameter or buffer changes
    data = cache.current(chain, grad=False)
    if data is None:
        return None
    key = (dtype, tuple(frames), posture, config, vel, damping, com, coll_key)
    problems = data.derived(_CACHE, dict)
    prob = problems.get(key)
    if prob is None:
        prob = _build(chain, key, limits, dt, VelocityLimit, Problem, com=com, collision=coll)
        if prob is None:
            return None
        if len(problems) > 64:  # a loop that builds new constants every step: keep the newest only
            problems.clear()
        prob.owned, problems[key] = True, prob
    if q.shape[-1] != prob.nq or (q_ref is not None and q_ref.shape[-1] != prob.nq):
        return None
    if q.ndim == 1:
        if (q_ref is not None and q_ref.ndim != 1) or any(t.ndim != 2 for t in targets) or \
                (com_target is not None and com_target.ndim != 1):
            return None
        if com_target is not None:
            if not math.isfinite(float(com_target.sum())):  # the torch path names it (dk_velocity_step
                return None  # checks the targets and q_ref)
            return prob.step(q if q.is_contiguous() else q.contiguous(), _stacked(targets), q_ref.contiguous()
                             if q_ref is not None else None, dt, com_target=com_target.contiguous())
        tgt = (targets[0] if len(targets) == 1 else torch.stack(targets)) if targets else None
        if tgt is not None and not tgt.is_contiguous():
            tgt = tgt.contiguous()
        if q_ref is not None and not q_ref.is_contiguous():
            q_ref = q_ref.contiguous()
        return prob.step(q if q.is_contiguous() else q.contiguous(), tgt, q_ref, dt)
    # NaN / inf targets or posture go to the torch path, whose validators name them (CPU tensors: no device
    # sync; a sum that overflows only costs the fast path); one row: dk_velocity_step checks them
    if not all(math.isfinite(float(x.sum())) for x in (*targets, *(() if q_ref is None else (q_ref,)),
                                                       *(() if com_target is None else (com_target,)))):
        return None
    batch, nq = q.shape[:-1], prob.nq
    B = q.numel() // nq
    try:
        tgt = torch.stack([t.expand(*batch, 4, 4) for t in targets], dim=-3).reshape(B, len(targets), 4, 4) \
            if targets else None
        ref = q_ref if q_ref is None or q_ref.ndim == 1 else q_ref.expand(*batch, nq).reshape(B, nq)
        ct = com_target if com_target is None or com_target.ndim == 1 else \
            com_target.expand(*batch, 3).reshape(B, 3)
    except RuntimeError:  # shapes that do not broadcast: the torch path says so
        return None
    q2 = q.reshape(B, nq)
    if not bool(torch.isfinite(q2).all()):  # the torch path's error
        return None
    try:
        v, _ = prob.solve(q2, tgt, ref, dt, com_target=ct)
    except RuntimeError:  # the chain cannot be packed now (a gradient wanted from its parameters)
        return None
    return v.reshape(*batch, prob.nv)


def _stacked(targets: list) -> Tensor | None:
    """The frame tasks' targets of one row as one contiguous ``(F, 4, 4)`` (None: no frame task)."""
    if not targets:
        return None
    tgt = targets[0] if len(targets) == 1 else torch.stack(targets)
    return tgt if tgt.is_contiguous() else tgt.contiguous()


def _build(chain, key, limits, dt, VelocityLimit, Problem, com=None, collision=None) -> NativeVelocity | None:
    """The :class:`NativeVelocity` of a route key (None: the chain or the constants do not suit it)."""
    dtype, frames, posture, config, vel, damping = key[:6]
    if chain.dtype is not dtype:
        return None
    K, names = chain.n_ends, list(getattr(chain, "end_links", None) or [])
    resolved = []
    for frame, pc, oc, g, lm in frames:
        if isinstance(frame, str):
            if frame not in names:
                return None
            frame = names.index(frame)
        if type(frame) is not int or not 0 <= frame < K:
            return None
        costs = [x for c in (pc, oc) for x in (c if isinstance(c, tuple) else (c,))]
        if min(costs) < 0 or g < 0 or lm < 0:
            return None
        resolved.append((frame, pc, oc, g, lm))
    if posture is not None:
        c = posture[0]
        if (isinstance(c, tuple) and len(c) != chain.nv) or min(c if isinstance(c, tuple) else (c,)) < 0 or \
                posture[1] < 0 or posture[2] < 0:
            return None
    if config is not None and not (type(config[0]) in _NUM and type(config[1]) in _NUM and
                                   0 < config[0] <= 1):
        return None
    vmax = None
    if vel is not None:
        try:
            probe = Problem(chain, torch.zeros(chain.nq, dtype=dtype), dt)
            vmax = next(lim for lim in limits if type(lim) is VelocityLimit).limits(probe)
        except Exception:  # noqa: BLE001 - any error: the torch path raises it with its own message
            return None
        vmax = vmax.detach().to("cpu", dtype)
        if vmax.ndim != 1 or vmax.shape[0] != chain.nv or not bool((vmax >= 0).all()):
            return None
    if com is not None:
        c = com[0]
        if min(c if isinstance(c, tuple) else (c,)) < 0 or com[1] < 0 or com[2] < 0 or \
                getattr(chain, "link_masses", None) is None or getattr(chain, "_mass_note", ""):
            return None  # the torch path raises (no masses) or warns (approximate masses) with its message
    coll = None if collision is None else (collision.collision, collision.world, collision.gain,
                                           collision.minimum_distance, collision.detection_distance)
    try:
        return NativeVelocity(chain, resolved, posture=posture, configuration_limit=config,
                              velocity_limit=vmax, damping=damping, dtype=dtype, com=com, collision=coll)
    except (ValueError, RuntimeError, TypeError):
        return None
