"""No ground penetration, exactly: the last step of the whole-clip optimisation.

The ``penetration`` rows of :func:`~diffkin.retarget.optimize_clip` are a penalty: they leave the sole a
fraction of a millimetre below the ground where the other terms pull it down (0.07 mm on the shipped turn).
The projection here removes that rest: in each frame where the lowest sole point of either foot is below
the ground by h > 0, the floating base is raised by h. A translation of the base moves every point of the
robot by the same vector, so the lowest sole point is then on the ground to rounding (|error| ~ 1e-16 m);
joint values, joint limits, horizontal foot motion (skating) and self-collision distances are unchanged;
only the heights, by at most h, change.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import ModelError
from .sole import Sole, sole_of

__all__ = ["lift_above_ground", "soles_of"]


def soles_of(chain, feet, sole: dict | None = None) -> list[Sole]:
    """The :class:`Sole` of each foot: ``sole[foot]`` where given, else read from the model
    (:func:`~diffkin.retarget.sole_of`)."""
    out = []
    for f in feet:
        s = (sole or {}).get(f) or sole_of(chain, f)
        if not isinstance(s, Sole):
            raise ModelError(f"sole[{f!r}] must be a Sole(points, radii), got {type(s).__name__}")
        out.append(s)
    return out


def lift_above_ground(chain, q: Tensor, feet, soles: list[Sole], ground: float = 0.0) -> Tensor:
    """``q (..., nq)`` (a floating base first: its position q[..., :3] in the chain's base frame) with the
    base raised along the world's z in each configuration by the depth of the lowest sole point of ``feet``
    below ``ground`` (module doc); configurations with both soles above the ground are returned unchanged."""
    if not chain.joint_kinds or chain.joint_kinds[0] != "free":
        raise ModelError("lift_above_ground needs a floating-base chain (a free joint first)")
    ends = list(chain.end_links)
    with torch.no_grad():
        T = chain.forward_kinematics(q, check=False)
        h = torch.stack([s.lowest(T[..., ends.index(f), :, :], ground)[0] for f, s in zip(feet, soles)],
                        -1).amin(-1)  # (...,): the lowest sole point of either foot above the ground
    lift = (-h).clamp_min(0).unsqueeze(-1)  # (..., 1): how far up, along the world's z
    base = chain.base
    # q[..., :3] is the base position in the chain's base frame T^b_0: the world's z is R_bᵀ e_z there
    up = q.new_tensor([0.0, 0.0, 1.0]) if base is None else base[2, :3].detach().to(q)
    return torch.cat((q[..., :3] + lift * up, q[..., 3:]), -1)
