"""The pose of every body of an MJCF model from an :class:`~diffkin.models.mjcf.MJCFChain`'s q.

A chain holds only the bodies on the paths to its end links; the viewer and
:meth:`diffkin.collision.RobotCollision.from_mjcf` need all of MuJoCo's bodies (hands, feet, a base welded
to the world). :func:`body_poses` puts the chain's q into the model's qpos (:meth:`MJCFChain.to_qpos`:
joints outside the chain at ``qpos0``, coupled joints following their leader) and evaluates one companion
chain of the same source whose end links are every body of the model, so each pose comes from the same
kinematic kernels as the chain's own FK (no second encoding of the MJCF frame rules).
"""

from __future__ import annotations

import warnings
import weakref

import torch
from torch import Tensor

from ..errors import ModelError

__all__ = ["body_poses", "body_names"]

_COMPANIONS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain -> {(dtype, device): chain}


def _source(chain):
    path, text = getattr(chain, "source_path", None), getattr(chain, "source_text", None)
    if path is None and text is None or not hasattr(chain, "to_qpos"):
        raise ModelError(f"expected an MJCF chain (diffkin.models.from_mjcf), got {type(chain).__name__}")
    return path or text


def _companion(chain):
    """The chain of the same source from the world to every body (cached per chain, dtype and device)."""
    from .mjcf import MJCFChain, compile_mjcf

    per = _COMPANIONS.setdefault(chain, {})
    key = (chain.dtype, chain.device)
    if key not in per:
        source = _source(chain)
        model, text, path = compile_mjcf(source)  # compiled once: its body names and the chain to them
        names = [model.body(b).name for b in range(1, model.nbody)]
        unnamed = [str(b + 1) for b, n in enumerate(names) if not n]
        if unnamed:
            raise ModelError(f"body_poses needs every body named; unnamed bodies (ids): {', '.join(unnamed)}")
        if not names:
            raise ModelError("the MJCF model has no body besides the world")
        with warnings.catch_warnings():  # the chain itself already said which equalities it ignores
            warnings.simplefilter("ignore")
            # the file's geometry, not learnable here: no autograd graph through its parameters
            per[key] = MJCFChain(model, text, path, names, dtype=chain.dtype,
                                 device=chain.device).requires_grad_(False)
    return per[key]


def body_names(chain) -> list[str]:
    """MuJoCo's body names of the chain's model, world first: the order of :func:`body_poses`."""
    return ["world", *_companion(chain).end_links]


def body_poses(chain, q: Tensor) -> Tensor:
    """World poses ``(..., nbody, 4, 4)`` of every body of an MJCF chain's model (MuJoCo's body order,
    the world body first, as ``mujoco.MjData.xpos`` / ``xmat``) for the chain's ``q (..., nq)``.

    Bodies off the chain's paths take the model's ``qpos0`` for their joints; joints coupled by a joint
    equality follow their leader (also where ``qpos0`` itself does not satisfy it). Differentiable in q; the
    geometry is the source file's (a calibrated chain's corrected parameters are not carried over).
    Use it as ``RobotCollision.from_mjcf(model, chain, body_poses=functools.partial(body_poses, chain))``.
    """
    q = chain.check_q(q)
    full = _companion(chain)
    T = full.forward_kinematics(full.from_qpos(chain.to_qpos(q)))  # (..., nbody - 1, 4, 4)
    world = torch.eye(4, dtype=T.dtype, device=T.device).expand(*T.shape[:-3], 1, 4, 4)
    return torch.cat((world, T), dim=-3)
