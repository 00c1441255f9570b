"""The learnable kinematic model (§2.8): one class for serial chains and trees, DH and URDF alike.

:class:`KinematicChain` is the one model. Its geometry is ``nn.Parameter`` s, turned into fixed transforms
around a motion about z per joint by :mod:`diffkin.kernels.joints`, and multiplied along a tree of joints by
:mod:`diffkin.kernels.tree`; the Jacobian (3.30) comes from :mod:`diffkin.kernels.jacobian`. Subclasses only
say what their parameters are and how they map to those transforms (:meth:`KinematicChain._geometry`):
:class:`DHChain` (a DH table, standard (2.52) or modified, optionally with Hayati's β) and
:class:`diffkin.models.URDFChain` (URDF joint origins and axes, trees with several end links, mimic joints).

Base and tool are learnable too: T_base = T_base,nominal · Δ(``base_delta``), T_tool = T_tool,nominal ·
Δ(``tool_delta``), with Δ a pose correction that stays rigid for any value (both deltas start at zero).

Learnable means able to learn, on request: the geometry is frozen (``requires_grad=False``) by default, so
that a solve or an FK call returns plain tensors and takes the constant fast path; ``learnable=True`` on
the constructor or loader, or ``chain.requires_grad_()``, makes it trainable.

The evaluations of the product, chosen in one place (:meth:`KinematicChain._route`):

* CPU calls that need no gradient (``torch.no_grad()``, or neither ``q`` nor a parameter requires grad): the
  fused C pass of :mod:`diffkin.kernels.native` (FK and Jacobian together, any batch size);
* otherwise, batches above :attr:`KinematicChain.small_batch`: batch last, joint after joint on the four
  columns of the current frame (few fused multiply-adds per joint, no 4×4 matmul);
* small batches: batch first, all link matrices at once, then one matmul per joint (fewer operations).

The last two are differentiable and traceable (``torch.compile``, ``torch.func``); all three compute the same
numbers to rounding. Under ``torch.autocast`` the kinematics run in the chain's dtype.

When no gradient w.r.t. geometry is needed (``torch.no_grad()`` or ``chain.requires_grad_(False)``) the
fixed transforms are evaluated once in float64 and used as Python constants whose zero terms are skipped
(kept on the chain's :class:`~diffkin.kernels.cache.Data` with every other fast path's derived state, and
remade by its one rule: optimizer steps, in-place updates, writes through ``.data``, replaced or moved
tensors and ``load_state_dict`` are all seen).
"""

from __future__ import annotations

from ..transforms import as_rigid_transform
from .dh import DHChain
from .kinematic import KinematicChain

__all__ = ["KinematicChain", "DHChain", "as_rigid_transform"]
