"""The artefact metrics of a robot clip (PHUMA's, defined exactly as issue 37 states them).

For a clip ``q (B, T, nq)`` at ``fps`` with foot contacts ``contacts (B, T, 2)`` (left, right), per clip:

* **joint-limit violations**: the number of (frame, joint) entries of the scalar joints (hinge, slide)
  beyond a limit, and the worst excess beyond it in rad (m for slides);
* **foot skating**: a contact phase is a maximal run of frames in contact of one foot; its skate is the
  horizontal (x, y) path length of the foot's sole centre over the run, ``Σ |c_t - c_{t-1}|`` over
  consecutive frames both in the run; the metric is the median over all contact phases of both feet, in
  mm (the mean of the two middle values for an even count; 0 without any contact phase);
* **ground penetration**: the maximum depth of the lowest sole point below the ground over all frames
  and both feet, in mm (0 when never below);
* **floating**: the mean height of the lowest sole point above the ground over the contact frames (both
  feet; a sole below the ground counts 0 here, penetration measures it), in mm (0 without contacts);
* **keypoint error** (with ``keypoints``): the mean distance of the chain's frames to the target points
  (the scaled human joints), in mm;
* **max joint velocity**: ``max |q_t - q_{t-1}| · fps`` over the scalar joints, in rad/s (m/s).

The sole and its centre are :mod:`diffkin.retarget.sole`'s (the lowest point of the foot's collision
geometry; the mean of its points).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ModelError, OptionError, ShapeError
from ..kernels.configuration import joint_kind
from ..validation import as_tensor, check_finite, check_number, shape_str
from .sole import Sole, sole_of

__all__ = ["Metrics", "metrics"]

@dataclass
class Metrics:
    """Per-clip artefact metrics, each ``(B,)`` (module doc). ``contact_phases`` counts the phases the
    skating median is taken over."""

    joint_limit_violations: Tensor
    joint_limit_excess: Tensor
    foot_skating: Tensor
    ground_penetration: Tensor
    floating: Tensor
    keypoint_error: Tensor | None
    max_joint_velocity: Tensor
    contact_phases: Tensor

    def as_dict(self) -> dict[str, list]:
        """The metrics as lists of Python numbers (one per clip), for tables and JSON."""
        return {k: (None if v is None else v.tolist()) for k, v in self.__dict__.items()}


def _finite(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        raise OptionError(f"expected {name} as a finite number (m), got {x!r}")
    return float(x)


def _scalar_columns(chain) -> list[int]:
    cols, i = [], 0
    for kind in chain.joint_kinds:
        w = joint_kind(kind).nq
        if w == 1:
            cols.append(i)
        i += w
    return cols


def _median_phase_skate(step: Tensor, both: Tensor, starts: Tensor) -> tuple[Tensor, Tensor]:
    """Median over each clip's contact phases of the phases' path lengths. ``step (B, F, T)``: |Δc| into
    frame t; ``both``: frames t and t-1 in the same phase; ``starts``: frame t starts a phase."""
    B = step.shape[0]
    n = starts.flatten(1).sum(-1)  # (B,) phases per clip
    phase = torch.cumsum(starts.flatten(), 0).reshape(starts.shape) - 1  # global phase id of each frame
    total = int(n.sum())
    lengths = torch.zeros(max(total, 1), dtype=step.dtype, device=step.device)
    idx = phase.clamp_min(0).flatten()
    lengths = lengths.index_add(0, idx, torch.where(both, step, torch.zeros_like(step)).flatten())
    first = torch.cumsum(n, 0) - n  # global id of each clip's first phase
    width = max(int(n.max()) if B else 0, 1)
    rank = torch.arange(width, device=step.device)
    valid = rank < n[:, None]
    gid = (first[:, None] + rank).clamp_max(max(total - 1, 0))
    padded = torch.where(valid, lengths[gid], torch.full_like(lengths[gid], float("inf")))
    srt = padded.sort(-1).values
    lo = ((n - 1).clamp_min(0) // 2)[:, None]
    hi = (n // 2).clamp_max(width - 1)[:, None]
    med = 0.5 * (srt.gather(1, lo) + srt.gather(1, hi)).squeeze(1)
    return torch.where(n > 0, med, torch.zeros_like(med)), n


def metrics(chain, q, contacts, fps, *, feet, ground: float = 0.0, keypoints=None, keypoint_frames=None,
            sole: dict | None = None) -> Metrics:
    """The artefact metrics of ``q (B, T, nq)`` (a ``(T, nq)`` clip is B = 1) on ``chain`` (module doc).

    Args:
        chain: the robot; its FK must include the two feet (and the keypoint frames).
        q: joint configurations ``(B, T, nq)`` in the chain's q order.
        contacts: booleans ``(B, T, 2)``: left and right foot in contact.
        fps: frames per second (> 0).
        feet: ``(left, right)`` foot frame names, among ``chain.end_links``.
        ground: the ground height (m).
        keypoints: optional targets ``(B, T, K, 3)`` (m) for ``keypoint_frames`` (default: all
            ``chain.end_links``, in order).
        sole: optional ``{foot: Sole}`` overriding the geometry read from the model.

    Returns a :class:`Metrics` (lengths in mm, angles in rad, velocities in rad/s).
    """
    fps = check_number(fps, "fps", unit=" frames per second")
    ground = _finite(ground, "ground")
    q = check_finite(as_tensor(q, "q", dtype=chain.dtype, device=chain.device), "q")
    if q.ndim == 2:
        q = q.unsqueeze(0)
    if q.ndim != 3 or q.shape[-1] != chain.nq:
        raise ShapeError(f"expected q of shape (B, T, {chain.nq}), got {shape_str(q.shape)}")
    c = torch.as_tensor(contacts, device=q.device)
    if c.ndim == 2:
        c = c.unsqueeze(0)
    if tuple(c.shape) != (*q.shape[:2], 2):
        raise ShapeError(f"expected contacts of shape {shape_str((*q.shape[:2], 2))} (B, T, 2) to match q, "
                         f"got {shape_str(c.shape)}")
    c = c.bool()
    feet = list(feet)
    ends = list(chain.end_links)
    if len(feet) != 2 or any(f not in ends for f in feet):
        raise ModelError(f"feet must be (left, right) among the chain's frames {ends}, got {feet}")
    T_all = chain.forward_kinematics(q)
    if T_all.ndim == q.ndim + 1:  # a single end link
        T_all = T_all.unsqueeze(-3)
    heights, centres = [], []
    for f in feet:
        s = (sole or {}).get(f) or sole_of(chain, f)
        if not isinstance(s, Sole):
            raise ModelError(f"sole[{f!r}] must be a Sole(points, radii), got {type(s).__name__}")
        h, ctr = s.lowest(T_all[..., ends.index(f), :, :], ground)
        heights.append(h)
        centres.append(ctr)
    h = torch.stack(heights, -1)  # (B, T, 2)
    ctr = torch.stack(centres, -2)[..., :2]  # (B, T, 2, 2): foot, xy
    # skating: horizontal path of the sole centre within each contact phase
    step = torch.zeros_like(h)
    step[:, 1:] = (ctr[:, 1:] - ctr[:, :-1]).norm(dim=-1)
    prev = torch.zeros_like(c)
    prev[:, 1:] = c[:, :-1]
    skate, phases = _median_phase_skate(step.transpose(1, 2), (c & prev).transpose(1, 2),
                                        (c & ~prev).transpose(1, 2))
    zero = torch.zeros_like(h)
    penetration = torch.maximum(-h, zero).flatten(1).amax(-1)
    n_contact = c.flatten(1).sum(-1)
    floating = torch.where(c, h.clamp_min(0), zero).flatten(1).sum(-1) / n_contact.clamp_min(1)
    # joint limits and velocities on the scalar joints
    cols = torch.tensor(_scalar_columns(chain), dtype=torch.long, device=q.device)
    qs = q.index_select(-1, cols)
    if chain.q_limits is not None:
        lim = chain.q_limits.index_select(0, cols)
        excess = torch.maximum(lim[:, 0] - qs, qs - lim[:, 1]).clamp_min(0)
    else:
        excess = torch.zeros_like(qs)
    excess = torch.nan_to_num(excess, posinf=0.0)
    violations = (excess > 0).flatten(1).sum(-1)
    worst = excess.flatten(1).amax(-1) if qs.shape[-1] else torch.zeros(q.shape[0], dtype=q.dtype)
    if q.shape[1] > 1 and qs.shape[-1]:
        vmax = (qs[:, 1:] - qs[:, :-1]).abs().flatten(1).amax(-1) * fps
    else:
        vmax = torch.zeros(q.shape[0], dtype=q.dtype, device=q.device)
    kp = None
    if keypoints is not None:
        frames = list(keypoint_frames) if keypoint_frames is not None else ends
        unknown = [f for f in frames if f not in ends]
        if unknown:
            raise ModelError(f"keypoint frames {unknown} are not among the chain's frames {ends}")
        x = check_finite(as_tensor(keypoints, "keypoints", dtype=q.dtype, device=q.device), "keypoints")
        if x.ndim == 3:
            x = x.unsqueeze(0)
        if tuple(x.shape) != (*q.shape[:2], len(frames), 3):
            raise ShapeError(f"expected keypoints of shape {shape_str((*q.shape[:2], len(frames), 3))}, got "
                             f"{shape_str(x.shape)}")
        idx = torch.tensor([ends.index(f) for f in frames], device=q.device)
        p = T_all[..., :3, 3].index_select(-2, idx)
        kp = (p - x).norm(dim=-1).flatten(1).mean(-1) * 1000.0
    return Metrics(violations, worst, skate * 1000.0, penetration * 1000.0, floating * 1000.0, kp, vmax,
                   phases)
