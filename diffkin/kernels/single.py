"""The lean single-call path: FK (2.50) and FK + geometric Jacobian (3.30) of ONE configuration ``q (n,)``.

A batch-1 call through the general dispatch spends most of its time in Python-side checks and tensor
round trips (the fused C pass itself takes about 1 µs for a Panda). :func:`fk` checks what it needs with
plain attribute tests (a plain contiguous CPU tensor of the chain's dtype, shape ``(n,)``, no gradient
wanted), takes the chain's :class:`~diffkin.kernels.cache.Data` and makes ONE foreign call, ``dk_fk_one``,
on q's own memory and fresh outputs.

The Data is checked on every call by the one rule of :mod:`diffkin.kernels.cache`, in two halves: the
data pointers of every parameter and buffer here (:func:`_current`), their bytes in C (``dk_fk_one``
compares the :class:`~diffkin.kernels.cache.Watch` snapshot before it computes anything: a few hundred
bytes for a Panda, and answers ``DK_STALE``). Either miss makes a new Data.

Anything else (a batch, CUDA, autograd, a traced call, a non-finite q, chains the C kernel does not take)
returns None and the general path serves the call, so results and errors are the general path's.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from . import cache, native
from .cache import Data, Watch

__all__ = ["fk", "entry", "Watch"]

_KEY = cache.KEY
_STALE = native.CONSTANTS["DK_STALE"]
_is_wrapped = torch._C._functorch.is_functorch_wrapped_tensor
_I64, _PTR = ctypes.c_int64, ctypes.c_void_p
_one: tuple = (None, None)  # (the loaded library, its dk_fk_one typed)


def _fk_one():
    """``dk_fk_one`` of the loaded library, typed once per library, through a ``PyDLL`` handle: it keeps
    the GIL for its microsecond (no release and re-acquire), and its arguments are plain addresses (no
    per-call type checks of ctypes pointers)."""
    global _one
    lib = native._lib
    if _one[0] is not lib:
        fn = ctypes.PyDLL(native._path).dk_fk_one
        fn.restype, fn.argtypes = _I64, [_PTR] * 5
        _one = (lib, fn)
    return _one[1]


def _current(chain, grad: bool) -> Data | None:
    """The chain's Data with its lean state when the chain's tensors are still at its pointers and none
    wants a gradient; the bytes are not compared here (the caller does: dk_fk_one, or :func:`entry`). None:
    not servable now."""
    d = chain.__dict__  # plain reads: nn.Module's attribute lookup costs a microsecond here
    hit, ts = d.get(_KEY), (*d["_parameters"].values(), *d["_buffers"].values())
    if grad:  # a loop, not any(<generator>): half the cost
        for t in ts:
            if t is not None and t.requires_grad:
                return None
    if hit is None or hit.base is None:
        return _lean(chain)
    try:  # cache.pointers, inline (a call costs here)
        ptrs = [0 if t is None else t.data_ptr() for t in ts]
    except RuntimeError:  # a tensor without storage (a torch.func wrapper): the general path
        return None
    if ptrs != hit.ptrs or hit.topo is not d["_topo"]:
        return _lean(chain)
    return hit


def _lean(chain) -> Data | None:
    """The chain's current Data by the whole rule, with its lean state (None where it cannot serve)."""
    if chain.device.type != "cpu":  # a chain elsewhere: the general path's device error
        return None
    data = cache.current(chain, grad=False)
    return None if data is None else data.lean(chain)


def _remade(chain) -> Data | None:
    """A new Data (after ``DK_STALE``: bytes written since the Data was made), with its lean state."""
    cache.drop(chain)
    return _lean(chain)


def entry(chain, x: Tensor, grad: bool | None = None) -> Data | None:
    """The chain's current :class:`~diffkin.kernels.cache.Data` with its lean state for a call on the
    plain CPU tensor ``x``, or None (general path).

    A hit needs every parameter and buffer at the pointer and with the bytes the Data was made from, and
    no gradient wanted from any of them (``grad``: whether gradients are wanted, default grad mode; False
    for a caller that runs without autograd); a miss makes a new Data.
    """
    if torch.compiler.is_compiling() or _is_wrapped(x) or not native.available():
        return None
    hit = _current(chain, torch.is_grad_enabled() if grad is None else grad)
    if hit is not None and not hit.watch.unchanged():
        hit = _remade(chain)
    return hit


def fk(chain, q, jacobian: bool = False, _retry: bool = True):
    """``T (4, 4)`` (``(K, 4, 4)`` for K end links), or ``(T, J (6, nv) / (K, 6, nv))`` with ``jacobian``,
    of one configuration ``q (nq,)``; None when the lean path does not apply (the caller's general path then
    serves the call)."""
    if type(q) is not Tensor or not q.is_cpu or q.ndim != 1 or not q.is_contiguous():
        return None
    grad = torch.is_grad_enabled()
    if (grad and q.requires_grad) or torch.compiler.is_compiling() or _is_wrapped(q) \
            or not native.available():
        return None
    hit = _current(chain, grad)
    if hit is None or q.dtype is not hit.dtype or q.numel() != hit.n:
        return None
    T = torch.empty_like(hit.T0)
    J = torch.empty_like(hit.J0) if jacobian else None
    one = _one[1] if _one[0] is native._lib else _fk_one()
    status = one(hit.base, hit.watch_addr, q.data_ptr(), T.data_ptr(),
                 J.data_ptr() if jacobian else None)
    if status == _STALE and _retry:  # bytes written in place since the Data was made: remade once
        _remade(chain)
        return fk(chain, q, jacobian, False)
    if status != 0:  # non-finite q (or a failure): the general path's error
        return None
    return (T, J) if jacobian else T
