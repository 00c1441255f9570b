"""Optional CPU peer baselines: Pinocchio looped from Python and Robotics Toolbox for Python's C++ paths.

The issues' speed targets compare diffkin, in the same run, with pytorch-kinematics (see
:mod:`benchmarks.common`) and with these non-torch peers. Every function here raises :class:`SkipPeer` (a
``RuntimeError`` with the reason) when its package is missing, so a benchmark can skip the row cleanly;
:func:`available_peers` tells which are importable. Install: ``pip install pin`` (Pinocchio 3.x/4.x wheels,
~380 MB) and ``pip install roboticstoolbox-python``. Both peers compute in float64 only.

Wiring (for bench_fk / bench_jacobian / bench_ik; B = 1 000 is plenty, loops scale linearly)::

    from benchmarks import peers
    q = chain.random_configuration((1000,), generator=...).detach().double().numpy()
    try:
        rate, T = peers.pinocchio_fk_rate(q)          # configs/s, (B, 4, 4)
        rows.append({"impl": "pinocchio (Python loop)", "configs_per_s": rate, ...})
    except peers.SkipPeer as e:
        print(f"[fk] {e}")
    rate, T = peers.rtb_fk_rate(q)                     # RTB ETS.eval on the (B, 7) batch: C++ loop
    rate, J = peers.pinocchio_jacobian_rate(q)         # (B, 6, 7) [linear; angular], base frame
    rate, J = peers.rtb_jacobian_rate(q)               # C++ ETS_jacob0, one call per configuration
    res = peers.rtb_ik_lm(T_targets)                   # PeerIK(q, converged, iterations, seconds, ...)
    res = peers.pinocchio_dls_ik(T_targets, seeds)     # Pinocchio's documented CLIK/DLS example, no limits

Rates are ``B / median seconds`` of ``repeats`` timed passes over all B configurations after a short
warm-up; the returned arrays come from the timed loop (so agreement with diffkin can be reported beside the
rate). The FK rates include writing each pose into a ``(B, 4, 4)`` array, as a user needs them
(``copy_out=False`` times Pinocchio's bare ``forwardKinematics`` + ``updateFramePlacement`` instead). IK
results carry the peer's own flag only: the caller re-checks ``q`` with diffkin's float64 FK and limits.

Frames: Pinocchio is built from ``diffkin/models/data/panda.urdf`` and reports frame ``panda_link8`` (the
flange), whose world frame is ``panda_link0``: the same base and end frames as ``models.load("panda")``
(agreement ~1e-16). RTB is built from diffkin's own DH table (:func:`rtb_from_chain`), so it matches any
DH model with zero joint offsets exactly; RTB cannot use its C++ code for a joint with a nonzero offset
(``theta`` of a revolute, ``d`` of a prismatic joint), where it falls back to slow Python.
"""

from __future__ import annotations

import functools
import importlib.util
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "SkipPeer",
    "PeerIK",
    "available_peers",
    "pinocchio_panda",
    "pinocchio_fk_rate",
    "pinocchio_jacobian_rate",
    "pinocchio_dls_ik",
    "rtb_from_chain",
    "rtb_panda",
    "rtb_fk_rate",
    "rtb_jacobian_rate",
    "rtb_ik_lm",
    "rtb_tol",
]

PANDA_URDF = Path(__file__).resolve().parents[1] / "diffkin" / "models" / "data" / "panda.urdf"
PANDA_END_LINK = "panda_link8"
_WARMUP = 50


class SkipPeer(RuntimeError):
    """A peer package is not installed (or cannot run here); the message says which and how to install."""


@dataclass
class PeerIK:
    """One peer IK run: ``q (B, n)``, the peer's own ``converged (B,)`` flag, ``iterations (B,)``, wall
    time of the whole batch and ``solves_per_s`` = B / seconds."""

    q: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    seconds: float
    solves_per_s: float


def available_peers() -> dict[str, bool]:
    """``{"pinocchio": bool, "rtb": bool}``: whether each peer package is importable."""
    return {"pinocchio": importlib.util.find_spec("pinocchio") is not None,
            "rtb": importlib.util.find_spec("roboticstoolbox") is not None}


def _import(name: str, pip_name: str):
    try:
        return importlib.import_module(name)
    except ImportError as e:
        raise SkipPeer(f"{name} is not installed (pip install {pip_name}): {e}") from None


def _as_q(q) -> np.ndarray:
    q = np.ascontiguousarray(np.asarray(q, dtype=np.float64))
    if q.ndim != 2:
        raise ValueError(f"q must have shape (B, n), got {q.shape}")
    return q


def _median_rate(fn, B: int, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return B / statistics.median(times)


# ----------------------------------------------------------------------------------------- Pinocchio


@functools.lru_cache(maxsize=4)
def pinocchio_panda(urdf: str | None = None, end_link: str = PANDA_END_LINK):
    """``(model, data, frame_id)``: Pinocchio model of ``urdf`` (default: diffkin's Panda URDF) and the id of
    ``end_link``'s frame. Cached; the ``data`` is shared, so do not use it from several threads."""
    pin = _import("pinocchio", "pin")
    xml = Path(urdf or PANDA_URDF).read_text()
    model = pin.buildModelFromXML(xml)
    if not model.existFrame(end_link):
        raise ValueError(f"frame {end_link!r} not in the URDF")
    return model, model.createData(), model.getFrameId(end_link)


def pinocchio_fk_rate(q, repeats: int = 5, copy_out: bool = True) -> tuple[float, np.ndarray]:
    """Pinocchio FK looped from Python: ``forwardKinematics`` + ``updateFramePlacement`` per configuration.

    q: (B, 7) float64 → (configurations/s, T (B, 4, 4) world → flange). ``copy_out`` includes copying each
    pose into T in the timed loop (default); False times the bare two calls and fills T afterwards.
    """
    pin = _import("pinocchio", "pin")
    model, data, fid = pinocchio_panda()
    q = _as_q(q)
    T = np.empty((len(q), 4, 4))
    fk, ufp = pin.forwardKinematics, pin.updateFramePlacement

    def with_copy(rows=q):
        for i, qi in enumerate(rows):
            fk(model, data, qi)
            T[i] = ufp(model, data, fid).homogeneous

    def bare():
        for qi in q:
            fk(model, data, qi)
            ufp(model, data, fid)

    with_copy(q[:_WARMUP])
    rate = _median_rate(with_copy if copy_out else bare, len(q), repeats)
    if not copy_out:
        with_copy()
    return rate, T


def pinocchio_jacobian_rate(q, repeats: int = 5) -> tuple[float, np.ndarray]:
    """Pinocchio ``computeFrameJacobian(..., LOCAL_WORLD_ALIGNED)`` looped from Python (one call per
    configuration, FK included): q (B, 7) → (Jacobians/s, J (B, 6, 7) rows [linear; angular] in the base
    frame at the flange origin, i.e. diffkin's geometric Jacobian (3.30))."""
    pin = _import("pinocchio", "pin")
    model, data, fid = pinocchio_panda()
    q = _as_q(q)
    J = np.empty((len(q), 6, model.nv))
    cfj, frame = pin.computeFrameJacobian, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED

    def loop(rows=q):
        for i, qi in enumerate(rows):
            J[i] = cfj(model, data, qi, fid, frame)

    loop(q[:_WARMUP])
    return _median_rate(loop, len(q), repeats), J


def pinocchio_dls_ik(T_targets, seeds=None, eps: float = 1e-4, it_max: int = 1000, dt: float = 1e-1,
                     damp: float = 1e-12, seed: int = 0) -> PeerIK:
    """Pinocchio's documented IK example (examples/inverse-kinematics.py: CLIK with damped least squares
    on the SE(3) log error, step ``dt``, stop when ‖log‖ < eps), one target at a time from Python.

    T_targets: (B, 4, 4) world → flange; seeds: (B, 7) start configurations (default: uniform within the
    limits, ``seed``). The example ignores joint limits, and so does this. The flange target is moved to
    the parent joint's frame (the example works on a joint), which leaves the error the same rigid motion.
    """
    pin = _import("pinocchio", "pin")
    model, data, fid = pinocchio_panda()
    T_targets = np.asarray(T_targets, dtype=np.float64)
    B = len(T_targets)
    if seeds is None:
        rng = np.random.default_rng(seed)
        seeds = rng.uniform(model.lowerPositionLimit, model.upperPositionLimit, size=(B, model.nq))
    seeds = _as_q(seeds)
    jid, fMj = model.frames[fid].parentJoint, model.frames[fid].placement.inverse()
    q_out, ok, iters = np.empty_like(seeds), np.zeros(B, bool), np.zeros(B, np.int64)
    eye6 = np.eye(6)
    t0 = time.perf_counter()
    for b in range(B):
        oMdes = pin.SE3(T_targets[b]) * fMj
        q = seeds[b].copy()
        i = 0
        while True:
            pin.forwardKinematics(model, data, q)
            iMd = data.oMi[jid].actInv(oMdes)
            err = pin.log(iMd).vector
            if np.linalg.norm(err) < eps:
                ok[b] = True
                break
            if i >= it_max:
                break
            J = -pin.Jlog6(iMd.inverse()) @ pin.computeJointJacobian(model, data, q, jid)
            v = -J.T @ np.linalg.solve(J @ J.T + damp * eye6, err)
            q = pin.integrate(model, q, v * dt)
            i += 1
        q_out[b], iters[b] = q, i
    seconds = time.perf_counter() - t0
    return PeerIK(q_out, ok, iters, seconds, B / seconds)


# ------------------------------------------------------------------------------ Robotics Toolbox (RTB)


def rtb_from_chain(chain):
    """``roboticstoolbox.DHRobot`` with ``chain``'s DH table (standard or modified), joint types, limits,
    base and tool, in float64. Its ``.ets()`` runs RTB's C++ kernels when all joint offsets are zero."""
    rtb = _import("roboticstoolbox", "roboticstoolbox-python")
    from spatialmath import SE3

    tab = chain.dh_table().detach().to("cpu").double().numpy()  # columns a, alpha, d, theta
    lim = None if chain.q_limits is None else chain.q_limits.detach().to("cpu").double().numpy()
    modified = chain.convention == "modified"
    kinds = {("R", False): rtb.RevoluteDH, ("R", True): rtb.RevoluteMDH,
             ("P", False): rtb.PrismaticDH, ("P", True): rtb.PrismaticMDH}
    links = []
    for i, (a, alpha, d, theta) in enumerate(tab):
        kind = chain.joint_types[i]
        kw = {"a": a, "alpha": alpha, "qlim": None if lim is None else lim[i]}
        kw.update({"d": d, "offset": theta} if kind == "R" else {"theta": theta, "offset": d})
        links.append(kinds[kind, modified](**kw))
    extra = {}
    for name in ("base", "tool"):
        X = getattr(chain, name)
        if X is not None:
            extra[name] = SE3(X.detach().to("cpu").double().numpy(), check=False)
    return rtb.DHRobot(links, name=chain.name, **extra)


@functools.lru_cache(maxsize=1)
def rtb_panda():
    """RTB ETS of diffkin's Panda (modified DH to the flange, datasheet limits), cached."""
    import torch

    from diffkin import models

    return rtb_from_chain(models.load("panda", dtype=torch.float64)).ets()


def _ets(ets):
    return rtb_panda() if ets is None else ets


def rtb_fk_rate(q, repeats: int = 5, ets=None) -> tuple[float, np.ndarray]:
    """RTB's batched C++ FK: ``ETS.eval(q)`` on the whole (B, n) array (the loop over rows is in C++).

    q: (B, n) float64 → (configurations/s, T (B, 4, 4)). ``ets``: default :func:`rtb_panda`.
    (``ETS.fkine`` is the same call wrapped into an ``SE3`` list, ~5x slower.)
    """
    ets, q = _ets(ets), _as_q(q)
    ets.eval(q[:_WARMUP])
    out = {}

    def call():
        out["T"] = ets.eval(q)

    return _median_rate(call, len(q), repeats), out["T"]


def _jacob0_fn(ets):
    """RTB's C++ ``ETS_jacob0`` through its thin facade (skips ``ETS.jacob0``'s Python argument handling,
    ~2-4x faster per call); the public method where the C++ handle is absent."""
    try:
        from roboticstoolbox.ets.fknm import ETS_jacob0

        handle = ets._fknm
    except (ImportError, AttributeError):
        handle = None
    if handle is None:
        return ets.jacob0
    return lambda qi: ETS_jacob0(handle, qi, None)


def rtb_jacobian_rate(q, repeats: int = 5, ets=None, public_api: bool = False) -> tuple[float, np.ndarray]:
    """RTB geometric Jacobian in the base frame, one C++ call per configuration in a Python loop.

    q: (B, n) → (Jacobians/s, J (B, 6, n) [linear; angular]). ``public_api=True`` times ``ETS.jacob0``.
    """
    ets, q = _ets(ets), _as_q(q)
    jac = ets.jacob0 if public_api else _jacob0_fn(ets)
    J = np.empty((len(q), 6, q.shape[1]))

    def loop(rows=q):
        for i, qi in enumerate(rows):
            J[i] = jac(qi)

    loop(q[:_WARMUP])
    return _median_rate(loop, len(q), repeats), J


def rtb_tol(pos_tol: float = 1e-4, rot_tol: float = 1e-3) -> float:
    """ik_LM's residual bound E = ½‖e‖² (e = [Δp; angle·axis]) that guarantees both tolerances."""
    return 0.5 * min(pos_tol, rot_tol) ** 2


def rtb_ik_lm(T_targets, seeds=None, tol: float | None = None, ilimit: int = 30, slimit: int = 100,
              joint_limits: bool = True, method: str = "chan", k: float = 0.1, ets=None) -> PeerIK:
    """RTB's C++ Levenberg–Marquardt IK ``ETS.ik_LM``, one pose per call, restarts from random
    configurations (``slimit`` searches of ``ilimit`` iterations) and rejecting solutions outside the limits.

    T_targets: (B, 4, 4); seeds: optional (B, n) first-search starts; tol: default :func:`rtb_tol` () for
    0.1 mm / 1e-3 rad. Defaults are the fastest 100 %-success setting of a small sweep on the Panda
    (Chan damping with k = 0.1; k = 1.0, Sugihara and Wampler were slower or failed more).
    """
    ets = _ets(ets)
    T_targets = np.ascontiguousarray(np.asarray(T_targets, dtype=np.float64))
    tol = rtb_tol() if tol is None else tol
    B, n = len(T_targets), ets.n
    q_out, ok, iters = np.empty((B, n)), np.zeros(B, bool), np.zeros(B, np.int64)
    seeds = None if seeds is None else _as_q(seeds)
    kw = {"ilimit": ilimit, "slimit": slimit, "tol": tol, "joint_limits": joint_limits, "method": method,
          "k": k}
    t0 = time.perf_counter()
    for b in range(B):
        sol = ets.ik_LM(T_targets[b], q0=None if seeds is None else seeds[b], **kw)
        q_out[b], ok[b], iters[b] = sol.q, sol.success, sol.iterations
    seconds = time.perf_counter() - t0
    return PeerIK(q_out, ok, iters, seconds, B / seconds)
