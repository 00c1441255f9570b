"""The one way to evaluate FK on trusted input (no validation): for inner loops whose inputs a public
boundary already checked, and for ``torch.func`` transforms, which cannot run the host-side checks.

Library code that bypasses the validators calls :func:`fk` (or wraps a chain in :class:`UncheckedFK` for
``torch.func.functional_call``) instead of passing ``check=False`` itself, so that the bypass is one place;
only the chain's own methods (which own the validation) pass the flag. The environments, a separate package
on the public API, use the public ``check=False`` flag.
"""

from __future__ import annotations

from torch import Tensor, nn

__all__: list[str] = []


def fk(chain, q: Tensor, all_frames: bool = False) -> Tensor:
    """``chain.forward_kinematics(q)`` without input checks: ``(..., [K,] 4, 4)`` (``all_frames``:
    ``(..., J + 1, 4, 4)``); ``q`` must already be a validated ``(..., nq)`` tensor of the chain's dtype."""
    return chain.forward_kinematics(q, all_frames=all_frames, check=False)


class UncheckedFK(nn.Module):
    """A chain as a module whose forward is :func:`fk`, for ``torch.func.functional_call`` / ``vmap``
    over the chain's parameters (the calibration models)."""

    def __init__(self, chain):
        super().__init__()
        self.chain = chain

    def forward(self, q: Tensor) -> Tensor:
        return fk(self.chain, q)
