"""Self-collision rows of the whole-clip optimisation (:func:`~diffkin.retarget.optimize_clip`).

For the checked pairs of a :class:`~diffkin.collision.RobotCollision`, the inequality d_p(q_t) ≥ m (m the
margin) enters the Gauss–Newton as the residual

    r_{p,t} = w min(0, d_p(q_t) − m),    ∂r/∂δ = w [d_p < m] ∂d_p/∂q · ∂(q ⊕ δ)/∂δ,

zero while the pair is clear (the same one-sided penalty as the sole's ``penetration`` rows; with a weight
far above the keypoints' the equilibrium depth is ≈ (keypoint pull) / w², sub-millimetre).

Broad phase, once per round: the pairs are screened on the warm start. A pair is kept when it comes within
``m + screen`` in some frame of some clip; each iteration then evaluates only those pairs (the G1 of
Menagerie's MJX scene has 26 self pairs; on the shipped clips 13-22 are kept, the legs' and those of a
hand near a hip or an arm near the torso). The steps can move a limb farther than the screen (a hand
pushed out of the torso onto the hip): :meth:`SelfCollisionRows.extend` screens the result again and adds
the pairs found, and :func:`~diffkin.retarget.optimize_clip` then runs another round of iterations.

The distances are the collision layer's closed forms, their gradients one batched backward pass over all
frames (each frame's distance depends on that frame's q only, so ∂(Σ_t d_{p,t})/∂q_t = ∂d_{p,t}/∂q_t).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from ..errors import ModelError
from ..ik.residuals import _residual_jacobian

__all__ = ["G1_MJX_SCENE", "SelfCollisionRows", "g1_collision"]


class SelfCollisionRows:
    """The screened pairs of ``collision`` for the warm start ``q (B, T, nq)`` and their residual rows.

    ``pairs``: the names of the kept pairs (those within ``margin + screen`` in some frame at the warm
    start, and at each :meth:`extend`), ``count``: how many.
    """

    def __init__(self, collision, chain, q: Tensor, margin: float, screen: float):
        if not hasattr(collision, "self_distances") or not hasattr(collision, "_pair_index"):
            raise ModelError(f"collision must be a diffkin.collision.RobotCollision of the chain, got "
                             f"{type(collision).__name__}")
        collision._check_chain(chain, "retarget (collision=)")
        self.chain, self.collision, self.margin, self.screen = chain, collision, float(margin), float(screen)
        self.index: list[int] = []
        self.pairs: list[tuple[str, str]] = []
        self.count, self.model = 0, None
        self.extend(q)

    def extend(self, q: Tensor) -> bool:
        """Screen ``q (B, T, nq)`` (every pair of the collision model, one evaluation and one host read) and
        keep the pairs within ``margin + screen`` in some frame besides those kept; True when some were
        added."""
        B, T, nq = q.shape
        with torch.no_grad():
            d = self.collision.self_distances(q.reshape(B * T, nq))  # (B T, P)
            near = (d < self.margin + self.screen).any(0).nonzero().flatten().tolist()
        new = sorted(set(near) - set(self.index))
        if not new:
            return False
        self.index = sorted(set(self.index) | set(new))
        c = self.collision
        self.pairs = [c.pairs[i] for i in self.index]
        self.count = len(self.index)
        self.model = c._with_pairs([c._pair_index[i] for i in self.index]).requires_grad_(False)
        return True

    def distances(self, q: Tensor) -> Tensor:
        """The kept pairs' signed distances ``(B, T, P_kept)`` (metres; negative: penetration)."""
        B, T, nq = q.shape
        if self.model is None:
            return q.new_zeros(B, T, 0)
        return self.model.self_distances(q.reshape(B * T, nq)).reshape(B, T, -1)

    def rows(self, q: Tensor, weight: float) -> tuple[Tensor, Tensor]:
        """The residuals ``(B, T, P_kept)`` and their Jacobians ``(B, T, P_kept, nv)`` w.r.t. the step δ of
        :meth:`~diffkin.kernels.configuration.ConfigurationSpace.integrate` (module doc)."""
        B, T, nq = q.shape
        nv = self.chain.nv
        if self.model is None:
            return q.new_zeros(B, T, 0), q.new_zeros(B, T, 0, nv)
        with torch.enable_grad():
            qg = q.detach().reshape(B * T, nq).requires_grad_(True)
            d = self.model.self_distances(qg)  # (B T, P)
            Jq = _residual_jacobian(d, qg)  # (B T, P, nq)
        space = self.chain.configuration_space
        J = Jq if space.euclidean else Jq @ space.tangent_map(qg.detach())  # (B T, P, nv)
        d = d.detach()
        active = (d < self.margin).to(q.dtype) * weight
        r = active * (d - self.margin)
        J = active.unsqueeze(-1) * J.detach()
        return r.reshape(B, T, -1), J.reshape(B, T, -1, nv)


#: MuJoCo Menagerie's MJX G1 (29 DoF, rev 1.0): primitive colliders and the self pairs of its scene
#: (``diffkin/retarget/data/unitree_g1_mjx``, README there).
G1_MJX_SCENE = Path(__file__).resolve().parent / "data" / "unitree_g1_mjx" / "scene_mjx.xml"


def g1_collision(chain):
    """The self-collision model of the 29-DoF G1 for ``chain`` (an MJCF chain of Menagerie's current G1,
    e.g. ``models.from_mjcf(models.model_path("g1"), mapping.frames)``): the capsules, spheres and foot
    boxes of Menagerie's ``g1_mjx.xml`` and the 26 robot–robot ``<pair>``s of its ``scene_mjx.xml`` (legs
    against legs, hands against hips and thighs, the arms against the torso), placed by the chain's bodies.
    Its body tree must be that model's (same bodies, same order): :class:`~diffkin.errors.ModelError`
    otherwise. Pass it as ``retarget.clip(..., collision=)``."""
    import warnings

    from ..collision import RobotCollision
    from ..collision.mjcf import load_model

    if getattr(chain, "source_text", None) is None:
        raise ModelError(f"g1_collision needs an MJCF chain of the G1 (models.from_mjcf), got "
                         f"{type(chain).__name__}")
    with warnings.catch_warnings():  # the floor plane of the scene is not a robot geom: skipped
        warnings.simplefilter("ignore")
        scene = load_model(G1_MJX_SCENE)
        own = load_model(chain.source_path or chain.source_text)
    ours = [scene.body(b).name for b in range(scene.nbody)]
    theirs = [own.body(b).name for b in range(own.nbody)]
    if ours != theirs:
        raise ModelError(f"g1_collision: the chain's model has the bodies {theirs[1:4]}... ({len(theirs)}), "
                         f"not the 29-DoF G1's {ours[1:4]}... ({len(ours)})")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobotCollision.from_mjcf(scene, chain).requires_grad_(False)
