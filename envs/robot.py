"""The robot half of an env: a diffkin chain, its joint limits, and the two action mappings.

All methods are batched over the leading env axis ``(N, ...)`` and run with ``check=False`` on trusted,
already validated tensors (the envs validate actions once at the boundary).

* joint-velocity mode: ``a ∈ [-1, 1]^nv`` → q̇ = a · q̇_max, integrated over the control period on the
  configuration manifold (q ⊕ q̇ Δt, :meth:`~diffkin.chain.KinematicChain.integrate`: q + q̇ Δt for 1-DOF
  joints, q ⊗ exp(ω Δt / 2) for the quaternions of ball and free joints) and projected onto the joint limits.
* Cartesian mode: ``a ∈ [-1, 1]^3`` → Δx = a · Δx_max; q ⊕ q̇ Δt with q̇ ``(nv,)`` from
  :func:`diffkin.ik.velocity_step`: the damped-least-squares step (3.59) on the position rows, solved
  exactly under |q̇| ≤ q̇_max and the joint limits over Δt (limit-safe: a joint at its limit stops and the
  others take over the motion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from diffkin import models
from diffkin.chain import KinematicChain
from diffkin.errors import ConventionError, ModelError, ShapeError
from diffkin.ik.velocity import velocity_step
from diffkin.validation import check_device, shape_str, tensors

from ._checks import check_setting

__all__ = ["Robot", "RobotConfig", "load_chain", "robot_collision"]

# geometric parameters of a chain that domain randomisation perturbs, by unit (DHChain's names)
_LENGTH_PARAMS = ("a", "d")
_ANGLE_PARAMS = ("alpha", "theta", "beta")

def load_chain(robot: str | KinematicChain, dtype=torch.float32, device="cpu") -> KinematicChain:
    """A chain from a model name, a YAML / URDF / MJCF path or a chain instance (copied):
    :func:`diffkin.models.load_chain`."""
    return models.load_chain(robot, dtype=dtype, device=device)


@dataclass(frozen=True)
class RobotConfig:
    """Robot-side settings shared by every task."""

    max_joint_speed: float = 1.5  # rad/s (or m/s for prismatic joints)
    control_dt: float = 0.1  # s, one env step
    max_ee_step: float = 0.05  # m per step, Cartesian mode
    damping: float = 0.0025  # λ = k² of the damped least-squares step (3.59), m²
    # kinematic domain randomisation: an episode's DH lengths (a, d) are nominal + U(-1, 1) · this (m),
    # its angles (alpha, theta, beta) nominal + U(-1, 1) · geometry_noise_angle (rad); 0: the nominal robot
    geometry_noise_length: float = 0.0
    geometry_noise_angle: float = 0.0

    def __post_init__(self):
        for name in ("max_joint_speed", "control_dt", "max_ee_step", "damping"):
            check_setting(getattr(self, name), name, low=0.0, strict_low=True)
        for name in ("geometry_noise_length", "geometry_noise_angle"):
            check_setting(getattr(self, name), name, low=0.0)

    @property
    def randomized(self) -> bool:
        """Whether episodes draw their own geometry (a noise above 0)."""
        return self.geometry_noise_length > 0.0 or self.geometry_noise_angle > 0.0


class Robot:
    """Batched kinematic robot: FK, limits, and the joint / Cartesian action mappings."""

    def __init__(self, robot: str | KinematicChain = "panda", config: RobotConfig | None = None,
                 action_mode: str = "joint", home=None, dtype=torch.float32, device="cpu"):
        if action_mode not in ("joint", "cartesian"):
            raise ConventionError(f"action_mode must be 'joint' or 'cartesian', got {action_mode!r}")
        device = check_device(device)  # "cuda" without CUDA, "meta": DeviceError here, not deep in torch
        self.config = config or RobotConfig()
        self.chain = load_chain(robot, dtype=dtype, device=device).requires_grad_(False)
        self.name = robot if isinstance(robot, str) else self.chain.name
        self.space = self.chain.configuration_space
        self.n, self.nv = self.chain.nq, self.chain.nv  # coordinates of q; velocities (and joint actions)
        self.action_mode = action_mode
        self.action_dim = self.nv if action_mode == "joint" else 3
        self.dtype, self.device = dtype, torch.device(device)
        lo, hi = self.chain.lower_upper()
        self.lower, self.upper = lo.to(dtype).clone(), hi.to(dtype).clone()
        # what a step is clamped to: the ranges of the scalar coordinates (quaternion entries never: a unit
        # quaternion is within ±1 and a clamp would take it off the sphere)
        scalar = torch.zeros(self.n, dtype=torch.bool, device=self.device)
        scalar[list(self.space.scalar_index())] = True
        self._clamp = (torch.where(scalar, self.lower, -math.inf), torch.where(scalar, self.upper, math.inf))
        if home is None:  # the model's own start configuration, else the middle of the ranges
            home = self.chain.home if self.chain.home is not None else (self.lower + self.upper) / 2
        (home,) = tensors(("home", home, (self.n,)), like=self.chain)
        if home.ndim != 1:
            raise ShapeError(f"expected home of shape ({self.n},), got {shape_str(home.shape)}")
        # on the manifold: zero quaternions (the middle of ±1) become the identity, others unit length
        self.home = self.chain.clamp_to_limits(self.chain.normalize_configuration(home))
        self.step_limit = self.config.max_joint_speed * self.config.control_dt
        self.revolute = self.chain.revolute_mask.to(torch.bool)
        self.planar = self.chain.planar  # model data (YAML ``planar``), not a name
        self._position_rows = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=dtype, device=self.device)
        self._init_geometry()

    # ------------------------------------------------------------------------- domain randomisation
    def _init_geometry(self) -> None:
        """The perturbed parameters (name, nominal, noise) and their flat size ``geometry_dim``."""
        cfg = self.config
        params = dict(self.chain.named_parameters())
        noise = {**dict.fromkeys(_LENGTH_PARAMS, cfg.geometry_noise_length),
                 **dict.fromkeys(_ANGLE_PARAMS, cfg.geometry_noise_angle)}
        self._geo = [(k, params[k].detach(), noise[k]) for k in (*_LENGTH_PARAMS, *_ANGLE_PARAMS)
                     if params.get(k) is not None]
        if cfg.randomized and not self._geo:
            raise ModelError("geometry noise needs a DH chain (parameters "
                             f"{_LENGTH_PARAMS + _ANGLE_PARAMS}); "
                             f"{self.name!r} has {sorted(params)}")
        self.geometry_dim = sum(p.numel() for _, p, _ in self._geo) if cfg.randomized else 0
        self._fk = _EndPosition(self.chain)

    def nominal_geometry(self, n: int) -> Tensor:
        """The nominal perturbed parameters, flat, ``(n, geometry_dim)``."""
        flat = torch.cat([p.reshape(-1) for _, p, _ in self._geo]) if self.geometry_dim else \
            torch.zeros(0, dtype=self.dtype, device=self.device)
        return flat.expand(n, -1).clone()

    def sample_geometry(self, u: Tensor) -> Tensor:
        """Perturbed parameters ``(M, geometry_dim)`` from uniforms ``u (M, geometry_dim)``: nominal +
        ``(2u − 1) · noise`` (the length noise on a, d; the angle noise on alpha, theta, beta)."""
        scale = torch.cat([torch.full((p.numel(),), s, dtype=self.dtype, device=self.device)
                           for _, p, s in self._geo])
        return self.nominal_geometry(u.shape[0]) + (2.0 * u - 1.0) * scale

    def geometry_dict(self, flat: Tensor) -> dict[str, Tensor]:
        """Flat parameters ``(..., geometry_dim)`` → ``{name: (..., *shape)}`` for ``functional_call``."""
        out, i = {}, 0
        for k, p, _ in self._geo:
            out[k] = flat[..., i:i + p.numel()].reshape(*flat.shape[:-1], *p.shape)
            i += p.numel()
        return out

    # ------------------------------------------------------------------------------------ kinematics
    def ee_position(self, q: Tensor, geometry: Tensor | None = None) -> Tensor:
        """End-effector position ``(N, 3)`` from ``q (N, n)`` (2.50); with ``geometry (N, geometry_dim)``
        each row on its own robot: the one FK of the chain, ``torch.func.functional_call`` with that row's
        parameters, vectorised by ``torch.func.vmap``."""
        if geometry is None or geometry.shape[-1] == 0:
            return self.chain.forward_kinematics(q, check=False)[..., :3, 3]

        def one(params: dict[str, Tensor], qi: Tensor) -> Tensor:
            return torch.func.functional_call(self._fk, params, (qi[None],))[0]

        params = {f"chain.{k}": v for k, v in self.geometry_dict(geometry).items()}
        return torch.func.vmap(one)(params, q)

    def frames(self, q: Tensor) -> Tensor:
        """Origins of all frames ``(..., n + 1, 3)`` (for drawing)."""
        return self.chain.forward_kinematics(q, all_frames=True, check=False)[..., :3, 3]

    def normalize_q(self, q: Tensor) -> Tensor:
        """Joint positions mapped to [-1, 1] by the limits: 2 (q − lower) / (upper − lower) − 1, one
        multiply-add with the scale and shift computed once (an env step is a few dozen small ops)."""
        scale, shift = self._per_row(q, "affine")
        return torch.addcmul(shift, q, scale)

    def _per_row(self, q: Tensor, what: str) -> tuple[Tensor, Tensor]:
        """``(lower, upper)`` or ``(scale, shift)`` of :meth:`normalize_q` as contiguous ``q``-shaped tensors,
        made once per batch shape: an op broadcasting a ``(n,)`` row over ``(N, n)`` costs several times one
        on equal shapes (a 7-wide inner loop does not vectorise)."""
        cache = self.__dict__.setdefault("_rows", {})
        key = (what, tuple(q.shape))
        pair = cache.get(key)
        if pair is None:
            if what == "affine":
                scale = 2.0 / (self.upper - self.lower)
                row = (scale, -1.0 - self.lower * scale)
            else:
                row = self._clamp
            pair = cache[key] = tuple(t.expand(q.shape).contiguous() for t in row)
        return pair

    def sample_q(self, u: Tensor, spread: float = 1.0, around: Tensor | None = None) -> Tensor:
        """Configurations from uniforms ``u (N, nv)``: ``around + spread · (U(limits) − around)``, within
        the limits; on the manifold the geodesic from ``around`` to a uniform configuration (scalars uniform
        in their ranges, quaternions uniform on S³: :meth:`ConfigurationSpace.from_uniform`)."""
        around = self.home if around is None else around
        s = list(self.space.scalar_index())
        q = self.space.from_uniform(self.lower[s], self.upper[s], u)
        return self.space.interpolate(around.expand_as(q), q, spread)

    def perturbed_home(self, u: Tensor, noise: float) -> Tensor:
        """``home ⊕ noise · (2u − 1)`` from uniforms ``u (N, nv)``, projected onto the limits: the start
        configurations of an episode (``home + noise · U(-1, 1)^n`` for 1-DOF joints)."""
        return self.chain.clamp_to_limits(self.space.integrate(self.home, noise * (2.0 * u - 1.0)))

    def unbound(self, coords) -> None:
        """Lift the projection of a step onto the limits for the q coordinates ``coords`` (indices into
        ``(nq,)``): e.g. a free joint's translation, whose nominal range (the chain's ±1 m box) a reference
        clip walks out of. Later steps and :meth:`clamp` leave those coordinates as they are."""
        lo, hi = (t.clone() for t in self._clamp)
        lo[list(coords)], hi[list(coords)] = -math.inf, math.inf
        self._clamp = (lo, hi)
        self.__dict__.pop("_rows", None)  # the per-shape rows of the old bounds

    def clamp(self, q: Tensor) -> Tensor:
        """``q (N, nq)`` projected onto the joint limits the steps keep (scalar coordinates only), a new
        tensor."""
        return q.clamp(*self._per_row(q, "limits"))

    def velocity(self, q0: Tensor, q1: Tensor) -> Tensor:
        """The mean joint velocity ``(N, nv)`` over one control period from ``q0`` to ``q1``:
        (q1 ⊖ q0) / control_dt (angular velocities of ball joints in their child frames)."""
        return self.space.difference(q0, q1) / self.config.control_dt

    # -------------------------------------------------------------------------------------- actions
    def apply_action(self, q: Tensor, action: Tensor) -> Tensor:
        """Next configuration from ``q (N, nq)`` and a clipped action ``(N, action_dim)`` in [-1, 1]: q ⊕ Δ
        (:meth:`KinematicChain.integrate`; q + Δ for 1-DOF joints) with Δ = a · Δq_max in joint mode."""
        if self.action_mode == "joint":
            if self.space.euclidean:
                q = torch.add(q, action, alpha=self.step_limit)
            else:
                q = self.space.integrate(q, action * self.step_limit)
        else:
            q = self.space.integrate(q, self.cartesian_delta(q, action * self.config.max_ee_step))
        return q.clamp_(*self._per_row(q, "limits"))  # q is a new tensor here

    def cartesian_delta(self, q: Tensor, dx: Tensor) -> Tensor:
        """Δq ``(N, nv)`` for an end-effector displacement ``dx (N, 3)``: Δt ·
        :func:`~diffkin.ik.velocity_step` for the twist [Δx/Δt; 0] with weights (1, 1, 1, 0, 0, 0), damping
        λ = k² (3.59), |q̇| ≤ ``max_joint_speed`` and the joint limits over ``control_dt``."""
        cfg = self.config
        twist = torch.cat((dx / cfg.control_dt, torch.zeros_like(dx)), dim=-1)
        qd = velocity_step(self.chain, q, twist, cfg.control_dt, damping=cfg.damping,
                           velocity_limit=cfg.max_joint_speed, weight=self._position_rows)
        return qd * cfg.control_dt


class _EndPosition(nn.Module):
    """``q ↦ p_ee`` of a chain as a module, so ``functional_call`` can swap the chain's parameters (its
    ``forward`` would validate ``q``, which a ``vmap`` -ed call cannot)."""

    def __init__(self, chain: KinematicChain):
        super().__init__()
        self.chain = chain

    def forward(self, q: Tensor) -> Tensor:
        return self.chain.forward_kinematics(q, check=False)[..., :3, 3]


def robot_collision(chain: KinematicChain, collision=None):
    """The collision model a task checks on ``chain`` (the env's own copy): ``collision`` (a
    :class:`~diffkin.collision.RobotCollision`) copied onto the chain's dtype and device and bound to it, or,
    when None, one built from the robot's own description: the ``<collision>`` geoms of a URDF chain
    (:meth:`RobotCollision.from_urdf`, mesh files resolved from the chain's URDF text only, else skipped with
    a warning) or the geoms of an MJCF chain (:meth:`RobotCollision.from_mjcf`). A DH model carries no
    geometry: :class:`~diffkin.errors.ModelError` saying what to pass."""
    import copy

    from diffkin.collision import RobotCollision
    from diffkin.models import MJCFChain, URDFChain

    if collision is None:
        if isinstance(chain, URDFChain):
            collision = RobotCollision.from_urdf(chain.tree, chain)
        elif isinstance(chain, MJCFChain):
            collision = RobotCollision.from_mjcf(chain.source_path or chain.source_text, chain)
        else:
            raise ModelError(f"self-collision checks need collision geometry: robot {chain.name!r} "
                             f"({type(chain).__name__}) has none; pass collision=RobotCollision.from_urdf("
                             "...) or a URDF / MJCF chain (models.from_urdf, models.from_mjcf) as the robot")
        return collision.requires_grad_(False)
    if not isinstance(collision, RobotCollision):
        raise ModelError(f"expected collision as a diffkin.collision.RobotCollision, got "
                         f"{type(collision).__name__}")
    own = getattr(collision, "chain", None)
    if own is not None and (own.nq, own.nv) != (chain.nq, chain.nv):
        raise ShapeError(f"collision model for a chain of nq {own.nq}, nv {own.nv}; the robot has nq "
                         f"{chain.nq}, nv {chain.nv}")
    collision = copy.deepcopy(collision)
    # the chain is held by reference (to() converts the geometry only): the copy's own chain too, which an
    # MJCF model's body poses still read
    if collision.chain is not None:
        collision.chain.to(dtype=chain.dtype, device=chain.device)
    collision = collision.to(dtype=chain.dtype, device=chain.device)
    collision.chain = chain  # placed by the env's chain (its own copy of the robot)
    return collision.requires_grad_(False)
