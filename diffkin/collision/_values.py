"""A robot collision model's geometry and chain values as one hashable key: what constants derived from them
(the planner's joint reach and C constants, :mod:`diffkin.motion._edges`) are remembered for, so that the
copies one robot makes per scene (:meth:`RobotCollision.allow_collisions
<diffkin.collision.RobotCollision.allow_collisions>`) share them."""

from __future__ import annotations

import torch

__all__ = ["geometry_key", "share_geometry_key"]


def _own(collision) -> list:
    """The model's own geometry tensors (the chain's are watched by its state key)."""
    return [collision.capsule_a, collision.capsule_b, collision.capsule_radius, collision.box_center,
            collision.box_rpy, collision.box_half_extents, collision._col_anchor]


def _seen(collision, state, own: list) -> tuple:
    """What tells that the values are unchanged: the chain's state (a new one after any change of the
    chain's parameters or buffers), the convex count and each of ``own``'s version counter, storage, shape,
    dtype and device."""
    return (state, collision.convex_vertices.shape[0],
            tuple((t._version, t.data_ptr(), t.shape, t.dtype, t.device) for t in own))


def _state(collision):
    """The chain's state key (:meth:`~diffkin.chain.KinematicChain._state_key`: a new one after any change of
    its parameters or buffers), None where it may not be read as constants."""
    return getattr(collision.chain, "_state_key", lambda: None)()


def geometry_key(collision) -> tuple | None:
    """The geometry's and the chain's current values (and their dtype, device and shapes) and the chain's
    state as one hashable key; None where the chain's state may not be read as constants (nothing is
    remembered).

    Remembered on the model for its very tensors unchanged since (the same objects, kept alive there, their
    version counters, storage and shapes) and the chain's state: a model planning many scenes reads its
    values once (about 0.1 ms), and a copy made by :func:`share_geometry_key` takes its source's key without
    reading them."""
    state = _state(collision)
    if state is None:
        return None
    own = _own(collision)
    seen = _seen(collision, state, own)
    last = collision.__dict__.get("_geometry_key")
    # (an equal `seen` has as many tensors)
    if last is not None and last[1] == seen and all(a is b for a, b in zip(last[0], own)):
        return last[2]
    parts = [*own, *collision.chain.parameters()]
    with torch.no_grad():
        flat = torch.cat([t.reshape(-1) for t in parts]).to("cpu", torch.float64)  # (promoted: exact)
        key = (state, collision.capsule_a.dtype, collision.capsule_a.device, tuple(t.shape for t in parts),
               collision.convex_vertices.shape[0], flat.numpy().tobytes())
    collision.__dict__["_geometry_key"] = (own, seen, key)
    return key


def share_geometry_key(source, copy) -> None:
    """Give ``copy``, a model just made from ``source``'s current values on the same chain (equal tensors of
    its own, the same dtype, device and shapes), ``source``'s key (read once per source while its values
    stay: about 0.1 ms): the copy then reads nothing until its own tensors or the chain change."""
    key = geometry_key(source)
    if key is None:
        return
    own = _own(copy)
    state = key[0]  # the chain's state, as geometry_key read it just now (the chain is shared)
    copy.__dict__["_geometry_key"] = (own, _seen(copy, state, own), key)
