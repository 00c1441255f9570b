"""The checks a :class:`~diffkin.collision.RobotCollision` makes of its inputs (private): the chain, ``q`` and
the geometry in one dtype and device, and the chain a solver or sampler is given being the model's own."""

from __future__ import annotations

from torch import Tensor

from ..errors import DeviceError, DTypeError, ModelError

__all__: list[str] = []


def check_agree(rc, q: Tensor) -> None:
    """The geometry, the chain and q in one dtype and device (else a typed error naming them all)."""
    g, c = rc.capsule_radius, rc.chain
    named = [("the collision geometry", g.dtype, g.device), ("q", q.dtype, q.device)]
    if c is not None and hasattr(c, "dtype"):
        named.insert(1, ("the chain", c.dtype, c.device))
    if any(dt != named[0][1] for _, dt, _ in named):
        raise DTypeError("RobotCollision: " + ", ".join(f"{n} is {dt}" for n, dt, _ in named)
                         + "; convert them together (chain.double(); rc.double())")
    if any(dv != named[0][2] for *_, dv in named):
        raise DeviceError("RobotCollision: " + ", ".join(f"{n} is on {dv}" for n, _, dv in named)
                          + "; move them together (chain.to(device); rc.to(device))")


def check_chain(rc, chain, who: str) -> None:
    """``chain`` must be the chain ``rc`` places its geoms with (the same object): else
    :class:`~diffkin.errors.ModelError` naming both (``who``: the caller, for the message)."""
    own = rc.chain
    if own is None or own is chain:
        return
    raise ModelError(f"{who}: the collision model was built for {chain_str(own)}, but the chain given "
                     f"is {chain_str(chain)}; build it for this chain (RobotCollision.from_urdf(source, "
                     "chain) / from_mjcf(source, chain)) or rebind it (collision.chain = chain)")


def names_str(names: list[str], k: int = 4) -> str:
    """The first ``k`` names and the count."""
    return ", ".join(names[:k]) + (f", ... ({len(names)})" if len(names) > k else "")


def chain_str(chain) -> str:
    """A chain in an error message: its class, name and joint names."""
    names = list(getattr(chain, "joint_names", []) or [])
    shown = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
    name = getattr(chain, "name", None)
    return f"{type(chain).__name__}{f' {name!r}' if name else ''} (joints {shown or '?'}, id {id(chain):#x})"
