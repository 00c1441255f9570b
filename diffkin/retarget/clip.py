"""Retargeting a clip: per-clip scale, a frame-by-frame warm start through ``ik.solve`` (stage one), then
the whole-clip optimisation over all T frames of all B clips at once
(:func:`~diffkin.retarget.optimize_clip`: contacts held, no penetration, limits, smoothness), scored by
:func:`~diffkin.retarget.metrics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .. import ik
from ..errors import ModelError, OptionError
from ..kernels import native
from ..kernels.configuration import joint_kind
from ..validation import check_count
from .mapping import Mapping
from .metrics import Metrics, _scalar_columns, metrics
from .motion import Motion
from .whole_clip import optimize_clip

__all__ = ["RetargetResult", "clip", "fit_scale"]


@dataclass
class RetargetResult:
    """A retargeted clip: ``q (B, T, nq)`` in the chain's q order, ``contacts (B, T, 2)`` (left, right),
    ``metrics`` (:func:`~diffkin.retarget.metrics` of ``q``), ``scale (B,)``, ``keypoints (B, T, K, 3)``
    (the scaled human targets of ``keypoint_frames``), ``fps`` and the chain's ``joint_names``;
    ``warm_start``: the metrics of stage one (before the whole-clip optimisation), ``cost``: that
    optimisation's cost per iteration ``(iterations + 1, B)`` (None when it did not run)."""

    q: Tensor
    contacts: Tensor
    metrics: Metrics
    scale: Tensor
    keypoints: Tensor
    keypoint_frames: list[str]
    fps: float
    joint_names: list[str]
    scalar_columns: list[int]
    warm_start: Metrics | None = None
    cost: Tensor | None = None

    def save(self, path) -> Path:
        """An ``.npz`` with ``q (B, T, nq)``, ``qd (B, T, n)`` (the hinge/slide joints' velocities, central
        differences), ``root_pos (B, T, 3)`` and ``root_quat (B, T, 4)`` (w, x, y, z; when the first joint
        is free), ``contacts``, ``fps``, ``joint_names`` (of the qd columns), ``scale``."""
        path = Path(path)
        q = self.q.detach().cpu().double()
        qs = q[..., self.scalar_columns]
        qd = torch.gradient(qs, spacing=1.0 / self.fps, dim=1)[0] if q.shape[1] > 1 else torch.zeros_like(qs)
        names = [n for n in self.joint_names if n is not None]
        np.savez(path, q=q.numpy(), qd=qd.numpy(), root_pos=q[..., :3].numpy(), root_quat=q[..., 3:7].numpy(),
                 contacts=self.contacts.cpu().numpy(), fps=np.array(self.fps), joint_names=np.array(names),
                 scale=self.scale.detach().cpu().numpy())
        return path


def _reference(chain) -> Tensor:
    q = torch.zeros(chain.nq, dtype=chain.dtype, device=chain.device)
    if chain.joint_kinds and chain.joint_kinds[0] == "free":
        q[3] = 1.0
    return q


def _initial(chain, X: Tensor, kp: list, root: str, feet, window: int) -> Tensor:
    """Initial configurations ``(B, T, nq)``: the zero posture with the base at the root keypoint, turned to
    the heading of the right-to-left foot line (averaged over ``window`` frames either side: walking
    swings that line about the heading), or unturned without both feet among the keypoints."""
    B, T = X.shape[:2]
    q = _reference(chain).expand(B, T, -1).clone()
    q[..., :3] = X[:, :, kp.index(root)]
    if all(f in kp for f in feet):
        d = (X[:, :, kp.index(feet[0])] - X[:, :, kp.index(feet[1])])[..., :2]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        if T > 1 and window > 0:  # moving average over ±window frames (edges: the frames there are)
            c = torch.nn.functional.pad(d.cumsum(1), (0, 0, 1, 0))
            t = torch.arange(T, device=X.device)
            lo, hi = (t - window).clamp_min(0), (t + window + 1).clamp_max(T)
            d = c[:, hi] - c[:, lo]
        yaw = torch.atan2(d[..., 1], d[..., 0]) - math.pi / 2
        q[..., 3], q[..., 6] = torch.cos(yaw / 2), torch.sin(yaw / 2)
    return q


def _orientation_targets(chain, motion: Motion, mapping: Mapping, Q: Tensor) -> Tensor | None:
    """Target rotations ``(B, T, K, 3, 3)`` of the keypoint frames: each human joint's frame times a constant
    per-clip offset, the rotation nearest the mean of Rₕᵀ R_robot over the warm start ``Q`` (the polar
    factor of their sum, det +1), since a human joint's frame and the robot link's differ by a rest-pose
    rotation no clip states. None when the motion has no orientations."""
    if motion.orientations is None:
        return None
    kp = mapping.keypoint_frames
    Rh = motion.orientations[:, :, motion.index(mapping.human_joints)]
    with torch.no_grad():
        Rr = chain.forward_kinematics(Q)[..., [list(chain.end_links).index(f) for f in kp], :3, :3]
    U, _, Vh = torch.linalg.svd((Rh.mT @ Rr).sum(1))  # (B, K, 3, 3)
    flip = torch.ones_like(U[..., 0, :])
    flip[..., -1] = torch.det(U @ Vh).sign()
    offset = (U * flip.unsqueeze(-2)) @ Vh
    return Rh @ offset.unsqueeze(1)


def fit_scale(chain, motion: Motion, mapping: Mapping) -> Tensor:
    """Per-clip scale ``(B,)``: the summed distances of the robot's keypoint frames to its root keypoint
    (the first paired frame that is not a foot, e.g. the pelvis) at the zero configuration, over the
    human's (mean over frames). A limb-length ratio over all mapped limbs."""
    kp = mapping.keypoint_frames
    roots = [f for f in kp if f not in mapping.feet]
    if not roots:
        raise ModelError("the mapping needs a paired frame besides the feet (a pelvis) to fit a scale")
    r = kp.index(roots[0])
    with torch.no_grad():
        T0 = chain.forward_kinematics(_reference(chain))
    P = T0[[chain.end_links.index(f) for f in kp], :3, 3]
    H = motion.positions[:, :, motion.index(mapping.human_joints)]
    robot = (P - P[r]).norm(dim=-1).sum()
    human = (H - H[:, :, r : r + 1]).norm(dim=-1).sum(-1).mean(-1)
    return (robot.to(human) / human).to(motion.positions.dtype)


def clip(chain, motion: Motion, mapping: Mapping, *, collision=None, ground: float = 0.0, scale=None,
         max_iterations: int = 20, contact_thresholds: dict | None = None, whole_clip: bool = True,
         iterations: int | None = None, costs: dict | None = None, solver: str = "banded",
         warm_start: str = "sequential", velocity_limit=None,
         collision_margin: float = 0.01, threads: int | None = None) -> RetargetResult:
    """Retarget ``motion`` (B clips) onto ``chain`` (a floating-base chain whose end links are
    ``mapping.frames``, e.g. ``models.from_mjcf(path, mapping.frames)``).

    Stage one: the human joints are scaled (``scale``: a number, ``(B,)``, or None for :func:`fit_scale`)
    and followed with position-only ``ik.solve`` (one seed, ``max_iterations``). ``warm_start="batched"``
    solves all frames of all clips in one call, each from the zero posture with the base at that frame's
    human root, turned to the heading of the line from the right to the left foot (averaged over ±0.5 s);
    ``"sequential"`` solves frame after frame, each from the previous frame's answer (the first as the
    batched one, unaveraged). Contacts come from the human clip
    (``mapping.contacts``; ``contact_thresholds`` overrides its ``height``/``speed``/``ground``).

    Stage two (``whole_clip=True``): :func:`~diffkin.retarget.optimize_clip` over all frames of all clips
    at once (``iterations``, ``costs``, ``solver``, ``velocity_limit`` are its: joint velocity limits as
    hard constraints, e.g. the motors' rad/s), with the mapping's position weights and soles; pairs with an
    orientation weight follow their human joint's frame (``motion.orientations``) up to a per-clip
    constant rotation fitted on stage one's answer. ``collision``: a
    :class:`~diffkin.collision.RobotCollision` of ``chain`` (e.g. :func:`~diffkin.retarget.g1_collision`)
    whose self pairs the optimisation keeps ``collision_margin`` (m) apart (pairs screened once on stage
    one's answer); None (the default) adds no self-collision rows, and stage one never sees collisions.
    ``iterations`` defaults to 10, or 20 with ``collision`` (stage one's hands can be 10 cm deep in the
    hips or torso on real clips: the one-sided penalty then takes more steps).
    No sole point ends below ``ground`` (the optimisation's last step raises the base where one is). The
    metrics are :func:`~diffkin.retarget.metrics` of the result; ``warm_start`` holds stage one's.
    ``threads``: the C kernels' threads in both stages (the frames of the clips shared out over them),
    independent of torch's count (:func:`diffkin.kernels.native.threads`; None: their default policy).
    """
    if threads is not None:
        check_count(threads, "threads")
    with native.threads(threads):
        return _clip(chain, motion, mapping, collision, ground, scale, max_iterations, contact_thresholds,
                     whole_clip, iterations, costs, solver, warm_start, velocity_limit, collision_margin)


def _clip(chain, motion, mapping, collision, ground, scale, max_iterations, contact_thresholds, whole_clip,
          iterations, costs, solver, warm_start, velocity_limit, collision_margin) -> RetargetResult:
    """:func:`clip` (its arguments, in order) within its thread setting."""
    mapping.check(motion)
    check_count(max_iterations, "max_iterations")
    if warm_start not in ("batched", "sequential"):
        raise OptionError(f"warm_start must be 'batched' or 'sequential', got {warm_start!r}")
    if list(chain.end_links) != list(mapping.frames):
        raise ModelError(f"the chain's frames {list(chain.end_links)} must be the mapping's frames "
                         f"{mapping.frames} (build it with mapping.frames)")
    if not chain.joint_kinds or chain.joint_kinds[0] != "free":
        raise ModelError("clip needs a floating-base chain (a free joint first)")
    motion_c = motion if motion.positions.dtype == chain.dtype else Motion(  # checked once: converted only
        motion.positions.to(chain.dtype), motion.names, motion.fps,
        None if motion.orientations is None else motion.orientations.to(chain.dtype))
    s = fit_scale(chain, motion_c, mapping) if scale is None else torch.as_tensor(
        scale, dtype=chain.dtype, device=chain.device).reshape(-1).expand(motion.batch)
    X = mapping.targets(motion_c, s)  # (B, T, K, 3)
    B, T, K = X.shape[:3]
    kp = mapping.keypoint_frames
    ends = list(chain.end_links)
    tgt = X.new_zeros(B, T, len(ends), 3)  # positions: ik.solve's position_only input
    tgt[:, :, [ends.index(f) for f in kp]] = X
    root = [f for f in kp if f not in mapping.feet][0]
    if warm_start == "sequential":
        q = _initial(chain, X[:, :1], kp, root, mapping.feet, 1)[:, 0]
        out = []
        for t in range(T):  # over time: each frame's solve starts at the previous frame's answer
            q = ik.solve(chain, tgt[:, t], q, num_seeds=1, max_iterations=max_iterations,
                         position_only=True).q.detach()
            out.append(q)
        Q = torch.stack(out, 1)
    else:  # every frame at once, each from the zero posture placed at its own root and heading
        q = _initial(chain, X, kp, root, mapping.feet, max(1, round(motion.fps / 2)))
        Q = ik.solve(chain, tgt, q, num_seeds=1, max_iterations=max_iterations, position_only=True).q.detach()
    contacts = mapping.contacts(motion_c, **(contact_thresholds or {}))
    sole = mapping.sole or None
    m = metrics(chain, Q, contacts, motion.fps, feet=mapping.feet, ground=ground, keypoints=X,
                keypoint_frames=kp, sole=sole)
    warm, cost = None, None
    if iterations is None:
        iterations = 10 if collision is None else 20
    if whole_clip:
        weights = mapping.weights[[mapping.frames.index(f) for f in kp]]
        ori = _orientation_targets(chain, motion_c, mapping, Q) if bool((weights[:, 1] > 0).any()) else None
        opt = optimize_clip(chain, Q, X, contacts, feet=mapping.feet, keypoint_frames=kp, fps=motion.fps,
                            ground=ground, sole=sole, keypoint_weights=weights[:, 0], costs=costs,
                            iterations=iterations, solver=solver, velocity_limit=velocity_limit,
                            orientations=ori, orientation_weights=None if ori is None else weights[:, 1],
                            collision=collision, collision_margin=collision_margin)
        Q, cost, warm = opt.q, opt.cost, m
        m = metrics(chain, Q, contacts, motion.fps, feet=mapping.feet, ground=ground, keypoints=X,
                    keypoint_frames=kp, sole=sole)
    cols = _scalar_columns(chain)
    names = list(getattr(chain, "joint_names", []))
    kinds = list(chain.joint_kinds)
    scalar_names = [n for n, k in zip(names, kinds) if joint_kind(k).nq == 1]  # the names of cols
    return RetargetResult(Q, contacts, m, s, X, kp, motion.fps, scalar_names, cols, warm, cost)
