"""The evaluations of a :class:`~diffkin.chain.KinematicChain` (§2.8, §3): FK (2.50)–(2.51), the Jacobian
(3.30), the batch-last kernel of the solvers, and THE dispatch point between them
(:meth:`ChainEvaluation._route`), with the constant fixed transforms kept on the chain's
:class:`~diffkin.kernels.cache.Data` (the Model/Data split of :mod:`diffkin.kernels.cache`). A mixin of
:class:`~diffkin.chain.KinematicChain`: it reads the model's parameters, buffers and topology, and keeps
nothing of its own."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .._numerics import broadcast_shapes
from ..errors import ShapeError
from ..kernels import cache, native, single
from ..kernels.columns import columns_to_matrices, plan_of, stack_columns
from ..kernels.jacobian import tree_jacobian, tree_jacobian_rows
from ..kernels.tree import Segments, column_frames, matrix_frames
from ..transforms import check_transform
from ..validation import check_finite, shape_str, tensors

__all__ = ["ChainEvaluation"]

_CHUNK = 8192  # configurations per thread and slice of a large CPU batch (_fk_jacobian)


def _autocast(q: Tensor) -> bool:
    """True under ``torch.autocast`` for q's device: the kinematics then run with autocast turned off, in the
    chain's dtype (float16 / bfloat16 products would be off by millimetres; the pose is cheap either way)."""
    return torch.is_autocast_enabled(q.device.type)


def _is_plain(t: Tensor) -> bool:
    """An ordinary tensor (not a torch.func / compile wrapper), whose values can be read as constants."""
    if torch.compiler.is_compiling():  # under dynamo every tensor is a graph value (and the check traces)
        return False
    return type(t) in (Tensor, nn.Parameter) and not torch._C._functorch.is_functorch_wrapped_tensor(t)


class ChainEvaluation:
    """FK, Jacobians and the batch-last kernel of a chain, on its constants where they may be used (the
    chain's :class:`~diffkin.kernels.cache.Data`) and on its parameters otherwise; see the module doc."""

    def _state_key(self) -> int | None:
        """A key of the chain's state for caches kept elsewhere (collision models, the velocity IK's
        problems): the generation of its current Data (unique over all chains; a new one after every change
        the rule sees), or None where the geometry may not be read as constants now (a gradient wanted from
        it, a torch.func / compile wrapper: :func:`diffkin.kernels.cache.current`)."""
        data = cache.current(self)
        return None if data is None else data.generation

    def _constants(self) -> tuple[Segments, Segments] | None:
        """Both constant forms of :meth:`_constant_segments` from the current Data, or None (see
        :meth:`_state_key`)."""
        data = cache.current(self)
        return None if data is None else data.segments(self)

    def _segments(self, per_joint: bool, constants: bool = True) -> Segments:
        """The fixed transforms of every joint: per joint (column path) or stacked (matrix path); Python
        constants when allowed, else tensors that carry gradients to the parameters."""
        data = cache.current(self) if constants else None
        if data is not None:
            return data.segments(self)[0 if per_joint else 1]
        return self._tensor_segments(per_joint, constants)

    def _native_model(self, q: Tensor) -> native.NativeModel | None:
        """The packed constants for the fused native kernel (:mod:`diffkin.kernels.native`) when it may
        serve this call: a plain CPU tensor, nothing needing a gradient, not traced (compile / torch.func),
        the library built. None otherwise (the torch kernels serve it)."""
        if torch.compiler.is_compiling() or q.device.type != "cpu" or not _is_plain(q) \
                or (q.requires_grad and torch.is_grad_enabled()) or not native.available():
            return None
        data = cache.current(self)
        return None if data is None else data.native_model(self)

    def _route(self, q: Tensor, op: str) -> tuple[str, native.NativeModel | None]:
        """THE dispatch point: which evaluation serves a call of ``op`` on ``q`` (joints last, or joints
        first for ``"columns"``); returns ``(path, packed native constants or None)``.

        ``op``: ``"fk"`` (end poses), ``"axes"`` (joint axes and origins), ``"fk_jacobian"``, ``"columns"``
        (the batch-last kernel a solver calls, constants allowed) or ``"columns_traced"`` (it with the
        geometry as tensors, or axes asked for). Paths, in this order of preference:

        * ``"native"``: the fused C pass (CPU, no gradient, not traced, the library built; see
          :meth:`_native_model`), for ``fk`` (unless :meth:`compile_fk` ed), ``fk_jacobian`` and ``columns``;
        * ``"batch_first"``: all link matrices at once, then one matmul per joint, for batches of at most
          :attr:`small_batch` configurations and for Jacobians / axes that need a gradient;
        * ``"compiled"``: the ``torch.compile`` d FK of :meth:`compile_fk`;
        * ``"chunked"``: large CPU Jacobian batches without autograd, batch last in slices per thread;
        * ``"batch_last"``: joint after joint on the columns of the current frame (every other call).
        """
        if op == "columns_traced":
            return "batch_last", None
        if op != "axes" and not (op == "fk" and self._compiled_fk is not None):
            packed = self._native_model(q)
            if packed is not None:
                return "native", packed
        if op == "columns":
            return "batch_last", None
        B = q.shape[:-1].numel()
        grad = op != "fk" and self._grad_needed(q)
        if B <= self.small_batch or grad:
            return "batch_first", None
        if op == "fk" and self._compiled_fk is not None:
            return "compiled", None
        if op == "fk_jacobian" and q.device.type == "cpu" and not torch.compiler.is_compiling() \
                and B > 2 * _CHUNK * torch.get_num_threads():
            return "chunked", None
        return "batch_last", None

    def _tensor_segments(self, per_joint: bool, constants: bool) -> Segments:
        pre, offset, post, ends = self._geometry()
        base, tool = self._fixed_pose("base", constants), self._fixed_pose("tool", constants)
        ends = [tool if E is None else (E if tool is None else E @ tool) for E in ends]
        stacked = Segments(pre, offset, post, base, ends)
        if not per_joint:
            return stacked
        return Segments(None if pre is None else pre.unbind(0), None if offset is None else offset.unbind(0),
                        None if post is None else post.unbind(0), base, ends)

    def _constant_segments(self) -> tuple[Segments, Segments]:
        """Both forms evaluated once without autograd: plans from float64 values (exact), and stacked
        tensors in the chain's dtype."""
        with torch.no_grad():
            hi = self if self.dtype == torch.float64 else None
            pre, offset, post, ends = (hi or _as_float64(self))._geometry()
            src = hi or _as_float64(self)
            base, tool = src.base, src.tool
            ends = [tool if E is None else (E if tool is None else E @ tool) for E in ends]

            eps = torch.finfo(self.dtype).eps  # snap what the chain's dtype cannot tell from 0 or ±1

            def plans(T):
                return None if T is None else [plan_of(t, eps) for t in T.unbind(0)]

            per_joint = Segments(plans(pre), None if offset is None else offset.cpu().tolist(), plans(post),
                                 None if base is None else plan_of(base, eps),
                                 [None if E is None else plan_of(E, eps) for E in ends])
            dt, dev = self.dtype, self.device

            def cast(T):
                return None if T is None else T.to(dtype=dt, device=dev)

            stacked = Segments(cast(pre), cast(offset), cast(post), cast(base), [cast(E) for E in ends])
        return per_joint, stacked

    # -------------------------------------------------------------------------------------------- FK
    def _row_base(self, base, check: bool, batch: Sequence[int] | None = None, of: str = "q") -> Tensor:
        """Per-row base poses ``(..., 4, 4)`` by the rule (the chain's dtype and device), checked rigid; with
        ``batch`` (the batch dims of ``of``: q or the targets) their batch dims must broadcast with it
        (:class:`ShapeError` naming both, instead of a matmul error)."""
        (base,) = tensors(("base", base, (4, 4)), like=self)
        if batch is not None:
            try:
                broadcast_shapes(tuple(batch), base.shape[:-2])
            except RuntimeError:
                got = f"{of} {shape_str(tuple(batch))}, got base {shape_str(base.shape)}"
                raise ShapeError(f"expected base of shape (..., 4, 4) whose batch dims broadcast with those "
                                 f"of {got}") from None
        return check_transform(base, "base") if check else base

    def _in_world(self, T: Tensor, base: Tensor, per_end: bool) -> Tensor:
        return base @ T if not per_end else base.unsqueeze(-3) @ T

    def forward_kinematics(self, q: Tensor, all_frames: bool = False, check: bool = True,
                           base: Tensor | None = None) -> Tensor:
        """Direct kinematics T = base · A1(q1) ··· An(qn) · tool  (2.50)–(2.51), on a tree for every end link.

        Args:
            q: joint variables ``(..., nq)`` (rad for revolute, m for prismatic joints, unit quaternions for
                ball and free joints).
            all_frames: if True return ``(..., J + 1, 4, 4)``: the base frame and the frame of every joint
                (its child link; J = n without mimic joints). For a chain with one end link the last one is
                the end-effector pose (tool applied).
            check: validate ``q`` (shape, dtype, finiteness). Disable only in inner loops on trusted input.
            base: per-row poses of the chain's base in the world ``(..., 4, 4)`` (broadcasting with q's
                batch): T_world = base · T, so robots at different places are one call.

        Returns:
            ``(..., 4, 4)`` for a chain with one end link, ``(..., K, 4, 4)`` for K end links.
        """
        if base is None and not all_frames and self._compiled_fk is None:  # one q (n,): kernels/single.py
            if (T := single.fk(self, q)) is not None:
                return T
        if base is not None:
            T = self.forward_kinematics(q, all_frames, check)
            per_end = all_frames or not self._single_end
            B = self._row_base(base, check, T.shape[: T.ndim - (3 if per_end else 2)])
            return self._in_world(T, B, per_end)
        if check:
            q = self.check_q(q, finite=False)
        if _autocast(q):  # poses in the chain's dtype: half precision would move a Panda's flange by mm
            with torch.autocast(q.device.type, enabled=False):
                return self.forward_kinematics(q, all_frames, check)
        batch = q.shape[:-1]
        if all_frames:
            if check:
                check_finite(q, "q")
            return self._all_frames(q)
        path, packed = self._route(q, "fk")
        if path == "native":  # the fused C pass; it counts non-finite entries of q as it reads them
            T, _, bad = native.fk_jacobian(packed, q.reshape(-1, self.n_joints).contiguous())
            if bad and check:
                check_finite(q, "q")  # raises the validator's error
            return self._out(T.reshape(*batch, self.n_ends, 4, 4))
        if check:
            check_finite(q, "q")
        if path == "batch_first":
            ends = matrix_frames(q, self._topo, self._segments(per_joint=False), with_frames=False)[0]
            return self._out(ends)
        if path == "compiled":
            return self._compiled_fk(q)
        # one transposing copy gives every joint a contiguous row: each op below is a unit-stride pass
        qT = q.reshape(-1, self.n_joints).T.contiguous()
        ends = column_frames(qT.unbind(0), self._topo, self._segments(per_joint=True))[0]
        return self._out(_poses_from_columns(ends, qT).reshape(*batch, self.n_ends, 4, 4))

    def _all_frames(self, q: Tensor) -> Tensor:
        ends, frames, _, _ = matrix_frames(q, self._topo, self._segments(per_joint=False))
        seg = self._segments(per_joint=False)
        base = seg.base if seg.base is not None else torch.eye(4, dtype=q.dtype, device=q.device)
        if self._single_end and self._topo.ends[0] == self._topo.n_frames - 1:
            frames = torch.cat((frames[..., :-1, :, :], ends), dim=-3)
        return torch.cat((base.expand(*frames.shape[:-3], 1, 4, 4), frames), dim=-3)

    def forward(self, q: Tensor) -> Tensor:
        """Alias of :meth:`forward_kinematics` (end-link poses)."""
        return self.forward_kinematics(q)

    def joint_axes_origins(self, q: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Joint motion axes and origins in the base frame, and the end poses, from one FK pass.

        Returns ``(axes (..., J, 3), origins (..., J, 3), T (..., [K,] 4, 4))``: for joint i the unit vector
        z_{i-1} and a point p_{i-1} of its axis in (3.30) (one row per joint frame: J = n without mimic
        joints).
        """
        if check:
            q = self.check_q(q)
        if _autocast(q):
            with torch.autocast(q.device.type, enabled=False):
                return self.joint_axes_origins(q, check)
        batch = q.shape[:-1]
        if self._route(q, "axes")[0] == "batch_first":
            ends, _, axes, origins = matrix_frames(q, self._topo, self._segments(per_joint=False), True)
            return axes, origins, self._out(ends)
        qT = q.reshape(-1, self.n_joints).T.contiguous()
        m = qT.shape[1]
        _, ends, axes = self.batch_last(qT, with_axes=True, check=False)
        # batch-last (3, J, m) memory handed out as (..., J, 3) views (reshape, not view, to flatten them)
        z = torch.stack([a[0].expand(3, m) for a in axes], dim=1).permute(2, 1, 0)
        o = torch.stack([a[1].expand(3, m) for a in axes], dim=1).permute(2, 1, 0)
        T = _poses_from_columns(ends, qT)
        J = z.shape[1]
        return (z.reshape(*batch, J, 3), o.reshape(*batch, J, 3),
                self._out(T.reshape(*batch, self.n_ends, 4, 4)))

    def _grad_needed(self, q: Tensor) -> bool:
        params = self.parameters()
        return torch.is_grad_enabled() and (q.requires_grad or any(p.requires_grad for p in params))

    def _fk_jacobian(self, q: Tensor, check: bool = True,
                     base: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """End poses and geometric Jacobians (3.30) from one pass: ``(T (..., [K,] 4, 4),
        J (..., [K,] 6, nv))``. ``base`` (per-row world poses of the base ``(..., 4, 4)``): T in the world
        and J's rows rotated into it, diag(R, R) J.

        Large CPU batches without autograd run in slices of 8192 configurations per intra-op thread through
        the batch-last path, written straight into the outputs: every value is computed as for the whole
        batch (all operations are per configuration), but the frames and rows stay in cache.
        """
        if base is None and (TJ := single.fk(self, q, jacobian=True)) is not None:  # kernels/single.py
            return TJ
        if base is not None:
            T, J = self._fk_jacobian(q, check)
            B = self._row_base(base, check, T.shape[: T.ndim - (2 if self._single_end else 3)])
            R = B[..., :3, :3] if self._single_end else B[..., None, :3, :3]
            J = torch.cat((R @ J[..., :3, :], R @ J[..., 3:, :]), dim=-2)
            return self._in_world(T, B, not self._single_end), J
        if check:
            q = self.check_q(q, finite=False)
        if _autocast(q):
            with torch.autocast(q.device.type, enabled=False):
                return self._fk_jacobian(q, check)
        batch, n, K, nv = q.shape[:-1], self.n_joints, self.n_ends, self.nv
        path, packed = self._route(q, "fk_jacobian")
        if path == "native":  # the fused C pass (poses and Jacobians at once)
            T, Jac, bad = native.fk_jacobian(packed, q.reshape(-1, n).contiguous(), with_jacobian=True)
            if bad and check:
                check_finite(q, "q")
            return self._out(T.reshape(*batch, K, 4, 4)), self._out(Jac.reshape(*batch, K, 6, nv))
        if check:
            check_finite(q, "q")
        if path == "batch_first":
            ends, _, axes, origins = matrix_frames(q, self._topo, self._segments(per_joint=False), True)
            J = tree_jacobian(axes, origins, ends[..., :3, 3], self._joint_revolute, self._topo)
            return self._out(ends), self._out(J)
        if path == "batch_last":
            ends, J = self._batch_last_fk_jacobian(q.reshape(-1, n).T.contiguous())
            return self._out(ends.reshape(*batch, K, 4, 4)), self._out(J.reshape(*batch, K, 6, nv))
        B, chunk = batch.numel(), _CHUNK * torch.get_num_threads()
        qT = q.reshape(-1, n).T.contiguous()
        T, Jout = _new_poses(q, B, K), q.new_empty(B, K, 6, nv)
        for start in range(0, B, chunk):
            part = slice(start, min(start + chunk, B))
            rows, ends = self.batch_last(qT[:, part], with_jacobian=True, check=False)
            if K == 1:  # straight into the output (contiguous rows of T)
                columns_to_matrices(ends[0], T[part, 0])
            else:
                T[part] = _poses_from_columns(ends, qT[:, part])
            Jout[part] = rows.permute(2, 1, 0).unflatten(1, (K, 6))
        return self._out(T.reshape(*batch, K, 4, 4)), self._out(Jout.reshape(*batch, K, 6, nv))

    def _batch_last_fk_jacobian(self, qT: Tensor) -> tuple[Tensor, Tensor]:
        """``qT (n, m)`` -> ``(T (m, K, 4, 4), J (m, K, 6, n))`` through the batch-last path."""
        rows, ends = self.batch_last(qT, with_jacobian=True, check=False)
        return _poses_from_columns(ends, qT), rows.permute(2, 1, 0).unflatten(1, (self.n_ends, 6))

    def batch_last(self, qT: Tensor, with_jacobian: bool = False, constants: bool = True,
                   with_axes: bool = False, check: bool = True):
        """The batch-last kernel for solvers that keep their state batch last (:mod:`diffkin.ik`).

        ``qT (n, m)`` -> ``(J, ends)``: ``ends`` the K end frames as columns ``(x, y, z, p)``, each
        ``(3, m)`` or ``(3, 1)``; ``J`` (if ``with_jacobian``) the geometric Jacobian rows ``(n, 6K, m)``
        (row block k for end link k), else None. ``with_axes`` appends the list of J joint ``(axis, origin)``
        column pairs. ``check``: validate ``qT`` by the rule (solvers pass False on their trusted state).
        """
        if check:
            (qT,) = tensors(("qT", qT, None), like=self, finite=False)
            if qT.ndim != 2 or qT.shape[0] != self.n_joints:
                raise ShapeError(f"expected qT of shape ({self.n_joints}, m) (joints first, batch last) for "
                                 f"chain '{self.name}', got {shape_str(qT.shape)}")
            check_finite(qT, "qT")
        topo = self._topo
        path, packed = self._route(qT, "columns_traced" if with_axes or not constants else "columns")
        if path == "native":  # the fused C pass, handed out in this layout (one copy each)
            m, K = qT.shape[1], self.n_ends
            T, Jac, _ = native.fk_jacobian(packed, qT.T.contiguous(), with_jacobian)
            cols = T[..., :3, :].permute(3, 2, 1, 0).contiguous()  # (4 columns, 3, K, m)
            ends = [tuple(cols[c, :, k] for c in range(4)) for k in range(K)]
            rows = None if Jac is None else Jac.reshape(m, 6 * K, self.nv).permute(2, 1, 0).contiguous()
            return rows, ends
        qs = qT.unbind(0)
        ends, axes, _ = column_frames(qs, topo, self._segments(per_joint=True, constants=constants),
                                      with_axes=with_jacobian or with_axes)
        if not with_jacobian:
            return (None, ends, axes) if with_axes else (None, ends)
        rows = tree_jacobian_rows(axes, [f[3] for f in ends], self._joint_revolute, topo, qT.shape[1])
        return (rows, ends, axes) if with_axes else (rows, ends)

    def _functional_fk(self, qT: Tensor) -> Tensor:
        """End poses ``(m, K, 4, 4)`` from ``qT (n, m)`` without in-place writes or data-dependent branches:
        the function :meth:`compile_fk` traces."""
        _, ends = self.batch_last(qT, constants=False, check=False)
        return torch.stack([stack_columns(tuple(c.expand(3, qT.shape[1]) for c in f)) for f in ends], dim=1)

def _new_poses(like: Tensor, *shape: int) -> Tensor:
    out = like.new_empty(*shape, 4, 4)
    out[..., 3, :3] = 0.0
    out[..., 3, 3] = 1.0
    return out


_LINEAR_CORRECTION: dict = {}


def _zero_correction(delta: Tensor) -> Tensor:
    """Δ(δ) at δ = 0, the identity, as I + L δ with L the exact derivative of Δ there:
    dΔ = [[[dω]×, dt], [0, 0]] (used only while δ is exactly zero).

    The base and tool corrections sit at zero until something moves them; in grad mode this gives their
    exact gradient for one small matmul instead of the rotation-vector map. Second derivatives w.r.t. the
    correction itself are not exact here (the linear map has none; Δ's ½[ω]×² term does): a Hessian in
    ``base_delta`` / ``tool_delta`` at exactly zero needs them set off zero first (mixed q–δ terms are
    exact)."""
    key = (delta.dtype, delta.device)
    L = _LINEAR_CORRECTION.get(key)
    if L is None:
        L = torch.zeros(16, 6, dtype=delta.dtype, device=delta.device)
        entries = (((0, 3), 0, 1), ((1, 3), 1, 1), ((2, 3), 2, 1), ((2, 1), 3, 1), ((1, 2), 3, -1),
                   ((0, 2), 4, 1), ((2, 0), 4, -1), ((1, 0), 5, 1), ((0, 1), 5, -1))
        for (r, c), k, sign in entries:
            L[4 * r + c, k] = sign
        _LINEAR_CORRECTION[key] = L
    return torch.eye(4, dtype=delta.dtype, device=delta.device) + (L @ delta).view(4, 4)


def _poses_from_columns(ends, qT: Tensor) -> Tensor:
    """``(m, K, 4, 4)`` poses from the K end frames' batch-last columns (``qT (n, m)`` for dtype and size):
    each end written to its own contiguous block (strided writes across K are several times slower)."""
    m = qT.shape[1]
    if len(ends) == 1:
        return columns_to_matrices(ends[0], _new_poses(qT, m)).unsqueeze(1)
    return torch.stack([columns_to_matrices(f, _new_poses(qT, m)) for f in ends], dim=1)


def _as_float64(chain: nn.Module) -> nn.Module:
    """A float64 CPU view of a chain's parameters and buffers for exact constant evaluation."""
    import copy

    c = copy.copy(chain)  # shallow: swap in float64 parameters/buffers without touching the original
    c._parameters = {k: None if p is None else p.detach().double().cpu()
                     for k, p in chain._parameters.items()}
    c._buffers = {k: None if b is None else (b.double() if b.is_floating_point() else b).cpu()
                  for k, b in chain._buffers.items()}
    c.__dict__.pop(cache.KEY, None)  # the original's Data is not the copy's
    return c
