"""Foot contacts of a human clip, from foot-joint heights and speeds."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..errors import ShapeError
from ..validation import check_number
from .motion import Motion

__all__ = ["detect_contacts"]


def detect_contacts(motion: Motion, feet: Sequence, *, height: float = 0.12, speed: float = 0.5,
                    ground: float = 0.0) -> Tensor:
    """Booleans ``(B, T, 2)``: the left and right foot in contact with the ground.

    ``feet`` is ``(left, right)``, each a joint name or a list of the foot's joint names (ankle and toe).
    A foot is in contact at frame t when one of its joints is both less than ``height`` metres above
    ``ground`` and slower than ``speed`` m/s horizontally (central differences, one-sided at the clip's
    ends; a one-frame clip has speed 0). The thresholds are overridable; the defaults (0.12 m, 0.5 m/s) suit
    ankle and toe joints of adult walking clips: a standing adult's ankle joint is 0.08-0.11 m high (the
    shipped walk's stance ankle reaches 0.107 m while it rolls over the heel), the stance foot's joints move
    well under 0.5 m/s and the swing foot's above 1 m/s.
    """
    height = check_number(height, "height", unit=" m")
    speed = check_number(speed, "speed", unit=" m/s")
    feet = list(feet)
    if len(feet) != 2:
        raise ShapeError(f"expected feet as (left, right), got {len(feet)} entries")
    p = motion.positions
    if p.shape[1] > 1:
        v = torch.empty_like(p[..., :2])
        v[:, 1:-1] = (p[:, 2:, :, :2] - p[:, :-2, :, :2]) * (motion.fps / 2)
        v[:, 0] = (p[:, 1, :, :2] - p[:, 0, :, :2]) * motion.fps
        v[:, -1] = (p[:, -1, :, :2] - p[:, -2, :, :2]) * motion.fps
        horizontal = v.norm(dim=-1)  # (B, T, J)
    else:
        horizontal = torch.zeros_like(p[..., 0])
    ok = (p[..., 2] - ground < height) & (horizontal < speed)  # (B, T, J)
    out = []
    for foot in feet:
        idx = motion.index([foot] if isinstance(foot, str) else list(foot))
        out.append(ok[..., idx].any(-1))
    return torch.stack(out, -1)
