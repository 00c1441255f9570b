"""Retargeting, stage two: one Gauss–Newton (Levenberg–Marquardt) optimisation over all T frames of all B
clips at once.

The unknowns are the configurations q_t of every frame; a step moves each by δ_t ``(nv,)`` (q_t ⊕ δ_t, the
chain's velocity coordinates). The cost is ½ Σ ‖r‖² over the residuals (w a weight of :data:`COSTS`):

=====================  =====================================================  ==========================
term                   residual                                               frames
=====================  =====================================================  ==========================
``keypoint``           w w_k (p_k(q_t) − x_{k,t}): the mapped frames on the     every frame
                       scaled human joints (``w_k`` the mapping's weights)
``orientation``        w w_o e_O(R_d, R_k(q_t)) (3.85): the mapped frames'      every frame (with
                       orientation on target rotations R_d (``w_o`` the     ``orientations``)
                       mapping's orientation weights)
``contact_height``     w (z_lowest − ground): the lowest sole point on the      a foot in contact
                       ground (no floating, no penetration)
``skating``            w (c_t − c_{t−1})_xy: the sole centre does not slide     both in one contact phase
``flat_foot``          w (R_f e_z)_xy: the sole level                           a foot in contact
``penetration``        w min(0, z_p − r_p − ground) for every sole point        every frame
``limit``              w (q − (q_max − m))⁺ − w ((q_min + m) − q)⁺              every frame (hinges)
``velocity_limit``     w (|Δq| − q̇_max/fps)⁺ sign(Δq), Δq = q_t − q_{t−1}        t ≥ 1 (hinges, slides; with
                                                                              ``velocity_limit``)
``velocity``           w (q_t ⊖ q_{t−1})                                        t ≥ 1
``acceleration``       w ((q_{t+1} ⊖ q_t) − (q_t ⊖ q_{t−1}))                     1 ≤ t ≤ T − 2
``posture``            w (q_t ⊖ q_t⁰): stay near the warm start q⁰              every frame
``collision``          w min(0, d_p(q_t) − m): self pairs p ≥ the margin m      every frame (with
                       (:mod:`~diffkin.retarget.self_collision`)              ``collision``)
=====================  =====================================================  ==========================

Point Jacobians come from the chain's geometric Jacobian (3.30) at the frame origin o: J_p = J_v − S(p − o)
J_ω (the velocity of a point of the body, (3.26)); the sole's normal R e_z moves as −S(R e_z) J_ω; the
orientation error e_O of (3.85) as −L J_ω with L of (3.87) (exact: ė_O = Lᵀω_d − Lω_e). The
difference terms take ∂(q_t ⊖ q_{t−1})/∂δ ≈ (I at t, −I at t−1) (exact for hinges and the base position).
The residuals couple at most three consecutive frames, so the normal matrix JᵀJ is block-banded with two
bands and each step is one block-banded Cholesky solve (:func:`diffkin.kernels.banded.block_banded_solve`,
O(T nv³)). A step is kept per clip when it lowers that clip's cost (the damping λ then shrinks, else it
grows); after each step the hinges are projected onto their limits (and, with ``velocity_limit``, frame
after frame onto [q_{t−1} − q̇_max/fps, q_{t−1} + q̇_max/fps] ∩ [q_min, q_max]), so the result never violates
them: hard constraints, whose penalty rows steer the steps away from the projection. The last step raises
the base wherever a sole is still below the ground (:func:`~diffkin.retarget.ground.lift_above_ground`), so
no sole point is below it (to rounding).

On CPU tensors without autograd the end links' rows (keypoint to skating) and their share of JᵀJ, Jᵀr and
the cost are formed in C (:func:`diffkin.kernels.native.clip_rows`), and so are the joint terms' (limit to
acceleration, with their differences ⊖: :func:`diffkin.kernels.native.clip_joint`), elsewhere in torch
ops (equal to rounding); further per-frame rows (the self-collision rows) plug in through
``_Terms.extra_rows`` (:meth:`_Terms.evaluate`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional as nn

from ..errors import ModelError, OptionError, ShapeError
from ..ik.closed_loop import _L_matrix
from ..jacobian import _shift_jacobian_point
from ..kernels import native
from ..kernels.banded import block_banded_cg, block_banded_solve
from ..kernels.pose_error import orientation_error
from ..rotations import _skew
from ..validation import as_tensor, check_count, check_finite, check_number, shape_str
from .ground import lift_above_ground, soles_of
from .metrics import _finite, _scalar_columns
from .self_collision import SelfCollisionRows

__all__ = ["COSTS", "ClipOptimization", "optimize_clip"]

#: default weights of the whole-clip terms (module doc); lengths in metres, angles in rad per frame.
COSTS = {"keypoint": 1.0, "orientation": 0.1, "contact_height": 30.0, "skating": 100.0, "flat_foot": 0.3,
         "penetration": 300.0, "limit": 10.0, "velocity_limit": 10.0, "velocity": 0.02, "acceleration": 0.3,
         "posture": 0.01, "collision": 300.0}


@dataclass
class ClipOptimization:
    """The optimised clip ``q (B, T, nq)`` and the cost ½‖r‖² per clip after each iteration
    ``cost (iterations + 1, B)`` (row 0: the warm start; with ``collision``, one or two more rounds of
    ``iterations`` when pairs came near that the screen had left out)."""

    q: Tensor
    cost: Tensor


class _Terms:
    """The residual layout of one problem (weights, sole geometry, index maps)."""

    def __init__(self, chain, keypoints, contacts, feet, keypoint_frames, fps, ground, sole, kp_weights, w,
                 q_ref, limit_margin, velocity_limit=None, orientations=None, orientation_weights=None,
                 collision: SelfCollisionRows | None = None):
        ends = list(chain.end_links)
        self.chain, self.x, self.c, self.ground = chain, keypoints, contacts, ground
        self.w, self.q_ref = w, q_ref
        self._F = None
        self._buffers, self._turn = [None, None], 0  # frame_terms' recycled D, E (two sets in turn)
        # native.clip_rows's converted constants (per dtype), made at the first evaluation: the weights,
        # targets, contacts, soles and support must not change after it (or clear this dict)
        self._clip_args: dict = {}
        #: the residual-row interface: callables (q, Ta, Ja) -> (r (B, T, m), J (B, T, m, nv)), per-frame
        #: rows added to the problem (:meth:`evaluate`)
        self.extra_rows: list = []
        self.fps = fps
        self.kp_idx = [ends.index(f) for f in keypoint_frames]
        self.kp_w = kp_weights
        # orientation targets (B, T, K_o, 3, 3) of the keypoint frames with a weight > 0 (their indices)
        self.ori = None
        if orientations is not None and bool((orientation_weights > 0).any()):
            sel = (orientation_weights > 0).nonzero().flatten().tolist()
            self.ori = orientations[:, :, sel]
            self.ori_idx = [self.kp_idx[k] for k in sel]
            self.ori_w = orientation_weights[sel]
        self.feet_idx = [ends.index(f) for f in feet]
        # the columns each end link's Jacobian can be non-zero in: the C frame terms' Gram products skip
        # finding them per frame
        self.support = native.jacobian_support(chain.topology, chain.nv)
        self.sole_list = soles_of(chain, feet, sole)
        self.soles = [(s.points.to(keypoints), s.radii.to(keypoints)) for s in self.sole_list]
        if collision is not None:  # self pairs closer than the margin (module self_collision), C path or not
            self.extra_rows.append(lambda q, Ta, Ja: collision.rows(q, self.w["collision"]))
        cs = chain.configuration_space
        self.sq = torch.tensor(cs.scalar_index("q"), dtype=torch.long, device=keypoints.device)
        self.sv = torch.tensor(cs.scalar_index("v"), dtype=torch.long, device=keypoints.device)
        # the same columns as a slice where they are a run (a floating base then hinges): views, no gathers
        self.sq_cols = _as_slice(cs.scalar_index("q"), self.sq)
        self.sv_cols = _as_slice(cs.scalar_index("v"), self.sv)
        ql = chain.q_limits  # every q column's limits (±inf without): clamp_to_limits' C twin in step()
        if ql is None:
            ql = torch.tensor([-float("inf"), float("inf")], dtype=keypoints.dtype, device=keypoints.device)
            ql = ql.expand(chain.nq, 2)
        ql = ql.to(keypoints)
        self.q_bounds = (ql[:, 0], ql[:, 1])
        lim = ql.index_select(0, self.sq)  # the scalar coordinates' (the velocity clamp's bounds)
        self.lo_hard, self.hi_hard = lim[:, 0], lim[:, 1]
        self.lo, self.hi = lim[:, 0] + limit_margin, lim[:, 1] - limit_margin
        # q̇_max / fps (rad or m per frame) on the scalar q columns (inf on the base position)
        self.vstep = None if velocity_limit is None else velocity_limit.index_select(0, self.sq) / fps
        self._joint_weights = torch.tensor([w[k] for k in ("limit", "velocity_limit", "posture", "velocity",
                                                           "acceleration")], dtype=keypoints.dtype,
                                          device=keypoints.device)

    def project(self, q: Tensor) -> Tensor:
        """``q (B, T, nq)`` onto the joint limits and, with velocity limits, frame after frame onto
        [q_{t−1} − q̇_max/fps, q_{t−1} + q̇_max/fps] ∩ [q_min, q_max] on the scalar columns (a recursion over
        time: each frame's interval depends on the projected frame before it; it meets the limits' range
        because q_{t−1} is in it)."""
        q = self.chain.clamp_to_limits(q, check=False)
        if self.vstep is None or q.shape[1] < 2:
            return q
        qs = q.index_select(-1, self.sq)
        start, T = 1, q.shape[1]
        if q.device.type == "cpu":  # no device sync: the frames before the first step beyond (in any clip)
            # are their own projection (each within q̇_max/fps of the one before), the loop starts there
            beyond = ((qs[:, 1:] - qs[:, :-1]).abs() > self.vstep * (1 - 1e-9)).any(-1).any(0)
            hit = beyond.nonzero()
            if hit.numel() == 0:
                return q
            start = int(hit[0, 0]) + 1
            # all frames at once, each on the interval of the previous sweep's frame before it: after k
            # sweeps frames < start + k are final, and a sweep that changes nothing has met the recursion
            # (whose answer is unique): the same numbers as the loop below in a few sweeps, not T steps
            out = qs
            for _ in range(8):
                swept = self._velocity_clamp(out[:, start - 1:-1], qs[:, start:])
                new = torch.cat((out[:, :start], swept), 1)
                if torch.equal(new, out):
                    return q.index_copy(-1, self.sq, out)
                out, start = new, start + 1
            qs = torch.cat((out[:, :start], qs[:, start:]), 1)  # the final frames, then the rest as given
        out = list(qs[:, :start].unbind(1))
        for t in range(start, T):
            out.append(self._velocity_clamp(out[-1], qs[:, t]))
        return q.index_copy(-1, self.sq, torch.stack(out, 1))

    def step(self, q: Tensor, step: Tensor) -> Tensor:
        """The LM trial ``project(q ⊕ step)`` for ``q (B, T, nq)``, ``step (B, T, nv)``: in C on CPU tensors
        (:func:`diffkin.kernels.native.clip_step`, the frame-after-frame loop of :meth:`project`), else in
        torch ops; the same to rounding."""
        out = native.clip_step(q, step, self.chain.configuration_space, self.q_bounds,
                               (self.lo_hard, self.hi_hard), self.vstep)
        return out if out is not None else self.project(self.chain.configuration_space.integrate(q, step))

    def _velocity_clamp(self, before: Tensor, q: Tensor) -> Tensor:
        """Scalar columns ``q`` onto [before − q̇_max/fps, before + q̇_max/fps] ∩ [q_min, q_max]."""
        lo = torch.maximum(before - self.vstep, self.lo_hard)
        hi = torch.minimum(before + self.vstep, self.hi_hard)
        return torch.minimum(torch.maximum(q, lo), hi)

    def _frames(self, X: Tensor, idx: list[int]) -> Tensor:
        """``X[:, :, idx]`` (dim 2: the chain's end links), a view where ``idx`` is a run of frames."""
        if idx == list(range(idx[0], idx[0] + len(idx))):
            return X[:, :, idx[0]:idx[0] + len(idx)]
        return X.index_select(2, torch.tensor(idx, device=X.device))

    def evaluate(self, q: Tensor, recycle: bool = False):
        """cost ``(B,)`` and the normal equations' blocks D, E ``(B, T, nv, nv)``, F ``(T, nv, nv)`` (the
        same for every clip), g ``(B, T, nv)``.

        Three parts: the end links' frame terms (keypoints, orientations, the soles' contact, penetration,
        level and skating rows: :meth:`frame_terms`), the per-frame rows of :attr:`extra_rows` (the
        residual-row interface: each callable ``(q, Ta (B, T, E, 4, 4), Ja (B, T, E, 6, nv)) -> (r (B, T,
        m), J (B, T, m, nv))`` adds ½‖r‖² to the cost, JᵀJ to D and Jᵀr to g), then the joint terms
        (:meth:`_joint_terms`: limits, posture, the differences over time). ``recycle``: D and E may be
        the blocks of the recycling evaluation before the last (:meth:`frame_terms`), for a caller that
        keeps only the last one."""
        B, T, nq = q.shape
        flat = q.reshape(B * T, nq)
        model = None if self.extra_rows else self.chain._native_model(flat)
        if model is not None:  # the C frame terms with the FK in the same pass (no pose nor Jacobian kept)
            out = self._native_frame_terms(None, None, B, T, recycle, fk=(model, flat.contiguous()))
            if out is not None:
                return self._joint_terms(q, *out)
        Ta, Ja = self.chain.forward_kinematics_and_jacobian(flat, check=False)
        if Ta.ndim == 3:
            Ta, Ja = Ta.unsqueeze(-3), Ja.unsqueeze(-3)
        cost, D, E, g = self.frame_terms(Ta, Ja, B, T, recycle)
        Ta, Ja = Ta.reshape(B, T, *Ta.shape[1:]), Ja.reshape(B, T, *Ja.shape[1:])
        for rows in self.extra_rows:
            r, J = rows(q, Ta, Ja)
            cost = cost + 0.5 * r.square().flatten(1).sum(-1)
            D = D + J.mT @ J
            g = g + (J.mT @ r.unsqueeze(-1)).squeeze(-1)
        return self._joint_terms(q, cost, D, E, g)

    def frame_terms(self, Ta: Tensor, Ja: Tensor, B: int, T: int, recycle: bool = False):
        """The end links' terms from the poses ``Ta (B T, E, 4, 4)`` and Jacobians ``Ja (B T, E, 6, nv)``
        of the B clips' T frames: cost ``(B,)``, D, E ``(B, T, nv, nv)``, g ``(B, T, nv)``. In C on CPU
        tensors (:func:`diffkin.kernels.native.clip_rows`), else :meth:`_frame_terms_torch` (the same to
        rounding: a CUDA tensor, autograd, no C compiler). ``recycle``: the C path writes D and E into
        the blocks it made two recycling calls before (two sets in turn), so an iterative caller that
        keeps only the last evaluation's blocks does not have 2 B T nv² fresh reals allocated (and the
        pages faulted in) at every call."""
        out = self._native_frame_terms(Ta, Ja, B, T, recycle)
        if out is None:
            return self._frame_terms_torch(Ta.reshape(B, T, *Ta.shape[1:]), Ja.reshape(B, T, *Ja.shape[1:]))
        return out

    def _native_frame_terms(self, Ta: Tensor | None, Ja: Tensor | None, B: int, T: int, recycle: bool,
                            fk: tuple | None = None):
        """:meth:`frame_terms` by :func:`diffkin.kernels.native.clip_rows` (from ``Ta, Ja``, or from ``fk =
        (native model, q (B T, nq))`` in one pass with the FK), or None where it does not serve."""
        w, ori = self.w, self.ori is not None
        like = fk[1] if Ta is None else Ta
        buffers = self._buffers[self._turn] if recycle else None
        out = native.clip_rows(
            Ta, Ja, T=T, keypoint_ends=self.kp_idx, keypoint_weights=w["keypoint"] * self.kp_w.to(like),
            keypoints=self.x.reshape(B * T, -1, 3), orientation_ends=self.ori_idx if ori else [],
            orientation_weights=w["orientation"] * self.ori_w.to(like) if ori else None,
            orientations=self.ori.reshape(B * T, -1, 3, 3) if ori else None, feet=self.feet_idx,
            soles=self.soles, contacts=self.c.reshape(B * T, 2), weights=w, ground=self.ground, out=buffers,
            support=self.support, fk=fk, prepared=self._clip_args)
        if out is None:
            return None
        cost, D, E, g = out
        if recycle:
            self._buffers[self._turn] = (D, E)
            self._turn ^= 1
        nv = D.shape[-1]
        return (cost.reshape(B, T).sum(-1), D.reshape(B, T, nv, nv), E.reshape(B, T, nv, nv),
                g.reshape(B, T, nv))

    def _frame_terms_torch(self, Ta: Tensor, Ja: Tensor):
        """:meth:`frame_terms` in torch ops, from ``Ta (B, T, E, 4, 4)`` and ``Ja (B, T, E, 6, nv)``.

        The rows of one frame (keypoints, the soles' contact, penetration and level rows) are stacked into
        ``J_f (B, T, m, nv)`` and enter D as one batched product J_fᵀ J_f; the skating rows couple
        consecutive frames, their diagonal part joins that product (each frame's sole-centre Jacobian
        weighted by the root of the summed squared weights of its two pairs), their off-diagonal part is
        one more product."""
        w = self.w
        B, T = Ta.shape[:2]
        nv = Ja.shape[-1]
        q = Ta  # the dtype and device of the rows
        rows, jacs, d_only = [], [], []  # d_only: rows entering D only (skating's diagonal part)
        # keypoints
        p = self._frames(Ta, self.kp_idx)[..., :3, 3]
        Jp = self._frames(Ja, self.kp_idx)[..., :3, :]
        sw = (w["keypoint"] * self.kp_w).to(q)[:, None]  # (K, 1)
        rows.append((sw * (p - self.x)).flatten(2))
        jacs.append((sw[..., None] * Jp).flatten(2, 3))
        if self.ori is not None:  # orientations: r = w e_O (3.85), ∂r/∂δ = −w L J_ω (3.87)
            R_e = self._frames(Ta, self.ori_idx)[..., :3, :3]
            e_o, _ = orientation_error(self.ori, R_e, "axis_angle")
            wo = (w["orientation"] * self.ori_w).to(q)[:, None]  # (K_o, 1)
            L = _L_matrix(self.ori, R_e)
            rows.append((wo * e_o).flatten(2))
            jacs.append((-wo[..., None] * (L @ self._frames(Ja, self.ori_idx)[..., 3:, :])).flatten(2, 3))
        cost = 0.0
        g = torch.zeros(B, T, nv, dtype=q.dtype, device=q.device)
        skate_new, skate_old = [], []  # the skating rows of frames t and t − 1, for E
        for k, (fi, (pts, rad)) in enumerate(zip(self.feet_idx, self.soles)):
            Tf, Jf = Ta[:, :, fi], Ja[:, :, fi]
            R, o = Tf[..., :3, :3], Tf[..., :3, 3]
            off = (R.unsqueeze(-3) @ pts.unsqueeze(-1)).squeeze(-1)  # (B, T, P, 3)
            world = off + o.unsqueeze(-2)
            Jpt = _shift_jacobian_point(Jf.unsqueeze(-3), off)[..., :3, :]  # (B, T, P, 3, nv): (3.112)
            h = world[..., 2] - rad - self.ground  # (B, T, P)
            c = self.c[..., k].to(q.dtype)  # (B, T)
            lowest = h.argmin(-1, keepdim=True)
            h_low = h.gather(-1, lowest).squeeze(-1)
            J_low = Jpt[..., 2, :].gather(-2, lowest.unsqueeze(-1).expand(B, T, 1, nv)).squeeze(-2)
            wc = w["contact_height"] * c
            rows.append((wc * h_low).unsqueeze(-1))
            jacs.append((wc.unsqueeze(-1) * J_low).unsqueeze(-2))
            below = (h < 0).to(q.dtype) * w["penetration"]
            rows.append(below * h)
            jacs.append(below.unsqueeze(-1) * Jpt[..., 2, :])
            n = R[..., :, 2]
            wf = (w["flat_foot"] * c)[..., None]
            rows.append(wf * n[..., :2])
            jacs.append(wf[..., None] * (-_skew(n) @ Jf[..., 3:, :])[..., :2, :])
            if T > 1:  # skating: the sole centre of consecutive contact frames
                ctr, Jc = world.mean(-2)[..., :2], Jpt.mean(-3)[..., :2, :]
                both = (self.c[:, 1:, k] & self.c[:, :-1, k]).to(q.dtype) * w["skating"]  # (B, T - 1)
                r = both[..., None] * (ctr[:, 1:] - ctr[:, :-1])
                cost = cost + 0.5 * r.square().flatten(1).sum(-1)
                gr = (Jc.mT @ nn.pad(both[..., None] * r, (0, 0, 1, 0)).unsqueeze(-1)).squeeze(-1)
                g += gr - (Jc.mT @ nn.pad(both[..., None] * r, (0, 0, 0, 1)).unsqueeze(-1)).squeeze(-1)
                wd = (nn.pad(both, (1, 0)).square() + nn.pad(both, (0, 1)).square()).sqrt()  # (B, T)
                d_only.append(wd[..., None, None] * Jc)
                skate_new.append(both[..., None, None] * Jc[:, 1:])
                skate_old.append(both[..., None, None] * Jc[:, :-1])
        r_f, J_f = torch.cat(rows, -1), torch.cat(jacs, -2)
        cost = cost + 0.5 * r_f.square().flatten(1).sum(-1)
        J_d = torch.cat((J_f, *d_only), -2) if d_only else J_f
        D = J_d.mT @ J_d
        g += (J_f.mT @ r_f.unsqueeze(-1)).squeeze(-1)
        E = torch.zeros_like(D)
        if skate_new:
            Jn, Jo = torch.cat(skate_new, -2), torch.cat(skate_old, -2)
            E[:, 1:] = -(Jn.mT @ Jo)
        return cost, D, E, g

    def _joint_terms(self, q: Tensor, cost: Tensor, D: Tensor, E: Tensor, g: Tensor):
        """The joint terms of ``q (B, T, nq)`` (limits, velocity limits, posture, velocity, acceleration;
        the module doc), multiples of the identity on the scalar columns or on all, added to the other
        terms' cost, D, E, g (D, E, g in place); returns (cost, D, E, F, g)."""
        w = self.w
        B, T, _ = q.shape
        nv = self.chain.nv
        cs = self.chain.configuration_space
        if native.clip_joint(q, self.q_ref, cs, self.lo, self.hi, self.vstep, self._joint_weights.to(q), cost,
                             D, E, g):  # C on CPU tensors: the same rows (the differences ⊖ there too)
            return cost, D, E, self._second_band(D), g
        # q ⊖ q_ref and the frame differences q_{t+1} ⊖ q_t in one call (one pass of the quaternion maps)
        both = cs.difference(torch.cat((self.q_ref, q[:, :-1]), 1), torch.cat((q, q[:, 1:]), 1))
        # joint limits (diagonal in the scalar velocity columns)
        qs = q[..., self.sq_cols]
        over, under = (qs - self.hi).clamp_min(0), (self.lo - qs).clamp_min(0)
        r_l = w["limit"] * (over - under)
        act = ((over > 0) | (under > 0)).to(q.dtype) * w["limit"] ** 2
        cost = cost + 0.5 * r_l.square().flatten(1).sum(-1)
        diag = torch.zeros(B, T, nv, dtype=q.dtype, device=q.device)
        diag[..., self.sv_cols] += act
        g[..., self.sv_cols] += w["limit"] * r_l
        if T > 1 and self.vstep is not None:  # velocity limits: ±(I, −I) on the scalar columns where beyond
            dq = qs[:, 1:] - qs[:, :-1]
            ex = (dq.abs() - self.vstep).clamp_min(0)
            wl = w["velocity_limit"]
            r_v = wl * ex * dq.sign()
            cost = cost + 0.5 * r_v.square().flatten(1).sum(-1)
            act = (ex > 0).to(q.dtype) * wl**2  # (B, T - 1, n_s)
            diag[:, 1:, self.sv_cols] += act
            diag[:, :-1, self.sv_cols] += act
            E[:, 1:].diagonal(dim1=-2, dim2=-1)[..., self.sv_cols] -= act
            g[:, 1:, self.sv_cols] += wl * r_v
            g[:, :-1, self.sv_cols] -= wl * r_v
        # posture: near the warm start
        dp, d = both[:, :T], both[:, T:]  # (B, T, nv), (B, T - 1, nv)
        cost = cost + 0.5 * (w["posture"] * dp).square().flatten(1).sum(-1)
        diag += w["posture"] ** 2
        g += w["posture"] ** 2 * dp
        if T > 1:  # velocity: J = (I at t, −I at t−1)
            wv = w["velocity"] ** 2
            cost = cost + 0.5 * wv * d.square().flatten(1).sum(-1)
            diag[:, 1:] += wv
            diag[:, :-1] += wv
            e = torch.full((T,), -wv, dtype=q.dtype, device=q.device)
            g[:, 1:] += wv * d
            g[:, :-1] -= wv * d
            if T > 2:  # acceleration: (+I, −2I, +I) at (t−1, t, t+1)
                a = d[:, 1:] - d[:, :-1]  # (B, T-2, nv), centred at frames 1..T-2
                wa = w["acceleration"] ** 2
                cost = cost + 0.5 * wa * a.square().flatten(1).sum(-1)
                diag[:, :-2] += wa
                diag[:, 1:-1] += 4 * wa
                diag[:, 2:] += wa
                e[1:-1] -= 2 * wa
                e[2:] -= 2 * wa
                g[:, :-2] += wa * a
                g[:, 1:-1] -= 2 * wa * a
                g[:, 2:] += wa * a
            e[0] = 0.0
            E.diagonal(dim1=-2, dim2=-1).add_(e[:, None])
        D.diagonal(dim1=-2, dim2=-1).add_(diag)
        return cost, D, E, self._second_band(D), g

    def _second_band(self, like: Tensor) -> Tensor:
        """F ``(T, nv, nv)``: the acceleration term's +w² I at (t, t − 2), t ≥ 2; the same for every q and
        every clip (made once; broadcast over the clips, the C solve reads it once for all of them)."""
        if self._F is None or self._F.shape != like.shape[1:]:
            F = like.new_zeros(like.shape[1:])
            if like.shape[1] > 2:
                F[2:].diagonal(dim1=-2, dim2=-1).fill_(self.w["acceleration"] ** 2)
            self._F = F
        return self._F


def _kept(ok: Tensor, old: tuple, new: tuple) -> list[Tensor]:
    """Per clip (dim 0) ``new`` where ``ok (B,)``, else ``old``. On CPU the rejected clips are copied into
    ``new`` (fresh tensors of this iteration; most clips keep their step, so little is copied), elsewhere
    one ``torch.where`` each (no host sync)."""
    if ok.device.type != "cpu":
        return [torch.where(ok.reshape(-1, *([1] * (a.ndim - 1))), b, a) for a, b in zip(old, new)]
    rejected = (~ok).nonzero().flatten()
    if rejected.numel():
        for a, b in zip(old, new):
            b.index_copy_(0, rejected, a.index_select(0, rejected))
    return list(new)


def _as_slice(index: list[int], tensor: Tensor):
    """``slice(a, b)`` where ``index`` is the run a, a + 1, ..., b − 1, else ``tensor`` (the same columns)."""
    if index and index == list(range(index[0], index[0] + len(index))):
        return slice(index[0], index[0] + len(index))
    return tensor


def _orientation_targets(orientations, weights, shape: tuple, like: Tensor):
    """Checked ``orientations (B, T, K, 3, 3)`` and ``weights (K,)`` (≥ 0) in ``like``'s dtype, or
    (None, None) without orientations."""
    if orientations is None:
        return None, None
    R = check_finite(as_tensor(orientations, "orientations", dtype=like.dtype, device=like.device),
                     "orientations")
    if tuple(R.shape) != (*shape, 3, 3):
        raise ShapeError(f"expected orientations of shape {shape_str((*shape, 3, 3))}, got "
                         f"{shape_str(R.shape)}")
    ow = torch.ones(shape[2], dtype=like.dtype, device=like.device) if weights is None else check_finite(
        as_tensor(weights, "orientation_weights", dtype=like.dtype, device=like.device).reshape(-1),
        "orientation_weights")
    if ow.shape[0] != shape[2] or bool((ow < 0).any()):
        raise OptionError(f"expected {shape[2]} orientation weights >= 0, got {ow.tolist()}")
    return R.detach(), ow


def _velocity_limits(chain, limit, like: Tensor) -> Tensor | None:
    """q̇_max ``(nq,)`` (inf outside the scalar joints) from a number, a sequence over the scalar joints
    (hinges, slides) or ``{joint name: limit}`` (inf: free), checked > 0; None for None."""
    if limit is None:
        return None
    names = [n for n, k in zip(chain.joint_names, chain.joint_kinds) if k not in ("free", "ball")]
    full = torch.full((chain.nq,), float("inf"), dtype=like.dtype, device=like.device)
    cols = torch.tensor(_scalar_columns(chain), dtype=torch.long, device=like.device)
    if isinstance(limit, dict):
        unknown = sorted(set(limit) - set(names))
        if unknown:
            raise ModelError(f"velocity_limit names joints {unknown} that are not scalar joints of the chain "
                             f"{names}")
        v = torch.full((len(names),), float("inf"), dtype=like.dtype, device=like.device)
        for name, value in limit.items():
            v[names.index(name)] = check_number(value, f"velocity_limit[{name!r}]", unit=" rad/s")
        return full.index_copy(0, cols, v)
    v = as_tensor(limit, "velocity_limit", dtype=like.dtype, device=like.device).reshape(-1)
    if v.numel() == 1:
        v = v.expand(len(names))
    if v.shape[0] != len(names):
        raise ShapeError(f"expected velocity_limit as a number or {len(names)} values (the scalar joints), "
                         f"got {v.shape[0]}")
    if bool(torch.isnan(v).any() | (v <= 0).any()):
        raise OptionError(f"expected velocity_limit > 0 (inf: free), got {v.tolist()}")
    return full.index_copy(0, cols, v)


def optimize_clip(chain, q, keypoints, contacts, *, feet, keypoint_frames, fps, ground: float = 0.0,
               sole: dict | None = None, keypoint_weights=None, costs: dict | None = None,
               iterations: int = 10, limit_margin: float = 0.0, damping: float = 1e-4, solver: str = "banded",
               cg_iterations: int = 30, velocity_limit=None, orientations=None,
               orientation_weights=None, collision=None, collision_margin: float = 0.01,
               collision_screen: float = 0.1, threads: int | None = None) -> ClipOptimization:
    """Optimise a warm-started clip ``q (B, T, nq)`` over all frames at once (module doc).

    Args:
        chain: the robot (a floating-base chain whose end links include ``feet`` and ``keypoint_frames``).
        q: the warm start ``(B, T, nq)`` (e.g. stage one of :func:`~diffkin.retarget.clip`).
        keypoints: targets ``(B, T, K, 3)`` (m) of ``keypoint_frames``.
        contacts: booleans ``(B, T, 2)``: the left and right foot in contact.
        feet: ``(left, right)`` foot frames among the chain's end links.
        keypoint_frames: the K frames the keypoints belong to.
        fps: frames per second (> 0; the weights are per frame, fps is checked and recorded only).
        ground: the ground height (m).
        sole: optional ``{foot: Sole}`` replacing the soles read from the model.
        keypoint_weights: optional ``(K,)`` position weights (the mapping's).
        costs: weights overriding :data:`COSTS` by name.
        iterations: Levenberg–Marquardt iterations (each one solve and one FK pass; 0 returns the warm
            start, clamped to the limits and raised onto the ground where a sole is below it).
        limit_margin: keep the hinges this far inside their limits (rad or m) where the cost allows.
        damping: the initial damping λ (relative to the mean diagonal of JᵀJ).
        solver: ``"banded"``, the exact block-banded Cholesky solve (a loop over T), or ``"cg"``,
            ``cg_iterations`` steps of block-Jacobi conjugate gradients (batched over T; for long clips on
            a GPU).

        orientations: optional target rotations ``(B, T, K, 3, 3)`` of ``keypoint_frames`` (world from
            frame), followed where ``orientation_weights (K,)`` (the mapping's) is > 0.
        velocity_limit: optional q̇_max of the scalar joints (hinges: rad/s, slides: m/s): a number for
            every one, ``(n_scalar,)`` in the chain's joint order, or ``{joint name: limit}`` (others
            free); kept as a hard constraint (module doc). None: no limit.
        collision: optional :class:`~diffkin.collision.RobotCollision` of ``chain`` (e.g.
            :func:`~diffkin.retarget.g1_collision`): its self pairs are kept ``collision_margin`` (m) apart
            (rows ``collision``); the pairs within ``collision_margin + collision_screen`` of each other in
            some frame of the warm start are screened in, the others not evaluated; after the iterations the
            screen is redone on the result, and where it finds pairs it had left out, they are added and
            ``iterations`` more run (at most twice; :mod:`~diffkin.retarget.self_collision`). None (the
            default): no self-collision rows.
        threads: the C kernels' threads (FK, frame terms, banded solve on CPU tensors: the clips' frames
            shared out over them) independently of ``torch.get_num_threads()``, capped by the free cores
            (:func:`diffkin.kernels.native.threads`); None: the kernels' default policy (torch's count
            for batches over 512 configurations, else one).

    Returns a :class:`ClipOptimization`.
    """
    check_number(fps, "fps", unit=" frames per second")
    check_count(iterations, "iterations", minimum=0)
    check_count(cg_iterations, "cg_iterations")
    if threads is not None:
        check_count(threads, "threads")
    if solver not in ("cg", "banded"):
        raise OptionError(f"solver must be 'cg' or 'banded', got {solver!r}")
    ground = _finite(ground, "ground")
    limit_margin = check_number(limit_margin, "limit_margin", positive=False)
    damping = check_number(damping, "damping")
    q = check_finite(as_tensor(q, "q", dtype=chain.dtype, device=chain.device), "q")
    if q.ndim != 3 or q.shape[-1] != chain.nq:
        raise ShapeError(f"expected q of shape (B, T, {chain.nq}), got {shape_str(q.shape)}")
    B, T = q.shape[:2]
    frames = list(keypoint_frames)
    ends = list(chain.end_links)
    unknown = [f for f in [*frames, *feet] if f not in ends]
    if unknown:
        raise ModelError(f"frames {unknown} are not among the chain's end links {ends}")
    x = check_finite(as_tensor(keypoints, "keypoints", dtype=q.dtype, device=q.device), "keypoints").to(q)
    if tuple(x.shape) != (B, T, len(frames), 3):
        raise ShapeError(f"expected keypoints of shape {shape_str((B, T, len(frames), 3))}, got "
                         f"{shape_str(x.shape)}")
    c = torch.as_tensor(contacts, device=q.device)
    if c.is_floating_point():  # 0/1 given as floats: NaN is not a contact state
        c = check_finite(c, "contacts")
        if not bool(((c == 0) | (c == 1)).all()):
            raise OptionError("expected contacts as booleans (or 0/1), got other values")
    if tuple(c.shape) != (B, T, 2):
        raise ShapeError(f"expected contacts of shape {shape_str((B, T, 2))}, got {shape_str(c.shape)}")
    unknown = sorted(set(costs or {}) - set(COSTS))
    if unknown:
        raise ModelError(f"costs names unknown terms {unknown}; the terms are {sorted(COSTS)}")
    for name, value in (costs or {}).items():
        check_number(value, f"costs[{name!r}]", positive=False)
    w = {**COSTS, **(costs or {})}
    kw = torch.ones(len(frames), dtype=q.dtype, device=q.device) if keypoint_weights is None else \
        as_tensor(keypoint_weights, "keypoint_weights", dtype=q.dtype, device=q.device).reshape(-1)
    if kw.shape[0] != len(frames):
        raise ShapeError(f"expected {len(frames)} keypoint weights, got {kw.shape[0]}")
    kw = check_finite(kw, "keypoint_weights").to(q)
    if bool((kw < 0).any()):
        raise OptionError("expected keypoint_weights >= 0")
    q = q.detach()
    collision_margin = check_number(collision_margin, "collision_margin", positive=False)
    collision_screen = check_number(collision_screen, "collision_screen", positive=False)
    rows = None if collision is None else SelfCollisionRows(collision, chain, q, collision_margin,
                                                            collision_screen)
    vmax = _velocity_limits(chain, velocity_limit, q)
    R_d, ow = _orientation_targets(orientations, orientation_weights, (B, T, len(frames)), q)
    terms = _Terms(chain, x.detach(), c.bool(), list(feet), frames, fps, ground, sole, kw, w, q.clone(),
                   limit_margin, vmax, R_d, ow, rows)
    q = terms.project(q)
    with torch.no_grad(), native.threads(threads):
        cur = terms.evaluate(q, recycle=True)  # only the last evaluation is kept: its blocks recycled
        lam = torch.full((B,), damping, dtype=q.dtype, device=q.device)
        history = [cur[0]]
        rounds = 1 if rows is None else 3  # with collision: re-screened after a round (module self_collision)
        for k in range(iterations * rounds):
            cost, D, E, F, g = cur
            scale = torch.diagonal(D, dim1=-2, dim2=-1).mean((-1, -2))  # (B,): λ relative to the curvature
            if solver == "cg":
                Dl = D.clone()  # D + λ s I: a copy, its diagonal raised (no full-size product with I)
                Dl.diagonal(dim1=-2, dim2=-1).add_((lam * scale)[:, None, None])
                step = -block_banded_cg(Dl, E, F, g, cg_iterations)
            else:  # D + λ s I as the solve's shift (the C path raises the diagonal as it copies D)
                step = -block_banded_solve(D, E, F, g, shift=lam * scale)
            trial = terms.step(q, step)
            new = terms.evaluate(trial, recycle=True)
            ok = torch.isfinite(new[0]) & (new[0] < cost)
            # F is the same at every q: the other parts are taken per clip from the trial where it is kept
            q, *kept = _kept(ok, (q, *cur[:3], cur[4]), (trial, *new[:3], new[4]))
            cur = (*kept[:3], F, kept[3])
            lam = torch.where(ok, lam * 0.5, lam * 4.0).clamp(1e-9, 1e6)
            history.append(cur[0])
            if rows is not None and (k + 1) % iterations == 0:
                if k + 1 == iterations * rounds or not rows.extend(q):  # no pair came near unscreened
                    break
                cur = terms.evaluate(q, recycle=True)  # the cost with the pairs added
    if chain.joint_kinds and chain.joint_kinds[0] == "free":  # no sole below the ground, exactly
        q = lift_above_ground(chain, q, feet, terms.sole_list, ground)
    return ClipOptimization(q, torch.stack(history))
