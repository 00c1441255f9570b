"""The lean single-call path: FK (2.50) and FK + geometric Jacobian (3.30) of ONE configuration ``q (n,)``.

A batch-1 call through the general dispatch spends most of its time in Python-side checks and tensor
round trips (the fused C pass itself takes about 2 µs for a Panda). :func:`fk` checks what it needs with
plain attribute tests (a plain CPU tensor of the chain's dtype, shape ``(n,)``, contiguous, no gradient
wanted), takes the chain's :class:`~diffkin.kernels.native.Args` from a per-chain cache that is remade
when the chain's :meth:`~diffkin.chain.KinematicChain._state_key` changes (any parameter or buffer set,
replaced or updated in place), and calls ``dk_fk`` on q's own memory and a fresh output tensor. Anything
else (a batch, CUDA, autograd, a traced call, a non-finite q, chains the C kernel does not take) returns
None and the general path serves the call, so results and errors are the general path's.
"""

from __future__ import annotations

import ctypes
import weakref

import torch
from torch import Tensor

from . import native

__all__ = ["fk", "entry", "Entry"]

_cache: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # chain -> Entry


def _tensors(chain) -> tuple:
    return (*chain._parameters.values(), *chain._buffers.values())


class Entry:
    """A chain's cached call state: the tensors and versions it was validated at, the packed Args per dtype
    and ``extra`` (per-chain state of other lean callers, e.g. the IK solve's, dropped with the entry)."""

    __slots__ = ("ids", "versions", "tensors", "args", "extra", "dtype", "n", "shapes")

    def __init__(self, chain, ids, versions, tensors, args):
        self.ids, self.versions, self.tensors, self.args, self.extra = ids, versions, tensors, args, {}
        self.dtype, self.n, K = chain.dtype, chain.n_joints, chain.n_ends  # read once: properties cost µs
        nv = chain.nv  # Jacobian columns: velocities (a ball joint's quaternion has three)
        self.shapes = ((4, 4), (6, nv)) if chain.single_end else ((K, 4, 4), (K, 6, nv))


def entry(chain, x: Tensor) -> Entry | None:
    """The chain's cached :class:`Entry` for a call on the plain CPU tensor ``x``, or None (general path).

    A hit needs the very tensor objects at the versions that the last full
    :meth:`~diffkin.chain.KinematicChain._state_key` check accepted (a tensor set, replaced or updated in
    place misses), and no gradient wanted from any of them; a miss re-validates through ``_state_key``.
    """
    if torch.compiler.is_compiling() or torch._C._functorch.is_functorch_wrapped_tensor(x):
        return None
    ts, hit = _tensors(chain), _cache.get(chain)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in ts):
        return None
    ids = list(map(id, ts))
    versions = [None if t is None else t._version for t in ts]
    if hit is None or hit.ids != ids or hit.versions != versions:
        cpu = chain.device.type == "cpu"  # a chain elsewhere: the general path's device error
        packed = chain._native_model(x) if cpu and chain._state_key() is not None else None
        if packed is None:
            return None
        hit = Entry(chain, ids, versions, ts, packed)  # ts: the ids stay those of live objects
        _cache[chain] = hit
    return hit


def fk(chain, q, jacobian: bool = False):
    """``T (4, 4)`` (``(K, 4, 4)`` for K end links), or ``(T, J (6, nv) / (K, 6, nv))`` with ``jacobian``,
    of one configuration ``q (nq,)``; None when the lean path does not apply (the caller's general path then
    serves the call)."""
    if type(q) is not Tensor or q.ndim != 1 or q.device.type != "cpu" or not q.is_contiguous() \
            or (q.requires_grad and torch.is_grad_enabled()) or not native.available():
        return None
    hit = entry(chain, q)
    if hit is None or q.dtype != hit.dtype or q.shape[0] != hit.n:
        return None
    T = torch.empty(hit.shapes[0], dtype=q.dtype)
    J = torch.empty(hit.shapes[1], dtype=q.dtype) if jacobian else None
    args = native.Args.from_buffer_copy(hit.args.args[q.dtype])
    args.batch, args.nthreads, args.q, args.T = 1, 1, q.data_ptr(), T.data_ptr()
    args.jac = J.data_ptr() if jacobian else None
    if native._lib.dk_fk(ctypes.byref(args)) != 0:  # non-finite q (or a failure): the general path's error
        return None
    return (T, J) if jacobian else T
