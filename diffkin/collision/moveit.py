"""MoveIt PlanningScene YAML: the obstacles and the allowed-collision matrix of a scene file.

A MoveIt scene (``moveit_msgs/PlanningScene`` written as YAML, as MotionBenchMaker's ``scene*.yaml``) holds

::

    allowed_collision_matrix:
      entry_names: [panda_hand, panda_leftfinger, ...]
      entry_values: [[false, true, ...], ...]        # true: the pair may touch (is not checked)
    robot_state: {joint_state: {name: [...], position: [...]}}
    world:
      collision_objects:
        - id: Can1
          pose: {position: [x, y, z], orientation: [x, y, z, w]}     # optional, default identity
          primitives: [{type: cylinder, dimensions: [0.14, 0.03]}]    # shape_msgs/SolidPrimitive
          primitive_poses: [{position: [...], orientation: [...]}]    # relative to ``pose``

Quaternions are ROS's ``(x, y, z, w)``. Dimensions are ``shape_msgs/SolidPrimitive``'s: a box its full sizes
``[x, y, z]``, a sphere ``[radius]``, a cylinder ``[height, radius]`` along its local z axis (the type may be
the name or the message's number: 1 box, 2 sphere, 3 cylinder). Every pose is read in the scene's planning
frame, taken as the robot's base frame (the objects' ``header.frame_id`` and the scene's
``fixed_frame_transforms`` are not applied). Meshes, planes and cones are a
:class:`~diffkin.errors.ModelError` naming the object (no silent omission), as is every malformed entry.

:func:`read_scene` gives a :class:`Scene`: the primitives (:class:`Primitive`, one per primitive of each
object, in file order) and the allowed pairs; :meth:`Scene.to_world` builds the
:class:`~diffkin.collision.World`, and the allowed pairs between robot links become pair rules through
:meth:`diffkin.collision.RobotCollision.allow_collisions`. :func:`diffkin.collision.read_world` reads such a
file directly into a World.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..errors import ConventionError, ModelError
from ..rotations import quaternion_to_matrix
from .boxes import Box
from .world import World

__all__ = ["Primitive", "Scene", "read_scene", "is_moveit_scene", "scene_from_data"]

#: SolidPrimitive type numbers (shape_msgs) and names this reader takes, and the dimensions each has
_TYPES = {1: "box", 2: "sphere", 3: "cylinder", 4: "cone"}
_DIMS = {"box": 3, "sphere": 1, "cylinder": 2}

@dataclass(frozen=True)
class Primitive:
    """One solid of a scene: ``name`` (the object's id; ``id/k`` for the k-th primitive of an object with
    several), ``kind`` (``box``, ``sphere``, ``cylinder``), ``pose`` ``(4, 4)`` float64 (the primitive's
    frame in the planning frame: the object's pose times the primitive's) and ``dimensions`` as
    shape_msgs/SolidPrimitive (box ``[x, y, z]`` full sizes, sphere ``[r]``, cylinder ``[height, r]`` along
    the local z axis)."""

    name: str
    kind: str
    pose: Tensor
    dimensions: tuple[float, ...]


@dataclass(frozen=True)
class Scene:
    """A MoveIt scene: ``objects`` (:class:`Primitive` s, file order), ``allowed`` (the unordered name pairs
    whose allowed-collision entry is true: those pairs may touch and are not checked; the diagonal left
    out), ``acm_names`` (the matrix's entry names, ``()`` without a matrix), ``joint_state`` (the scene's
    robot state, name -> position) and ``name`` (the scene's name)."""

    objects: tuple[Primitive, ...]
    allowed: frozenset[frozenset[str]] = frozenset()
    acm_names: tuple[str, ...] = ()
    joint_state: Mapping[str, float] = field(default_factory=dict)
    name: str = ""

    def to_world(self, *, dtype: torch.dtype | None = None, device=None,
                 cylinders: str | None = None) -> World:
        """The obstacles as a :class:`~diffkin.collision.World` in ``dtype`` on ``device``: spheres, boxes
        (centre, rotation, half sizes) and cylinders (axis end points at ± height/2 along the local z axis,
        radius). ``cylinders``: ``"capsules"`` holds each cylinder as its enclosing capsule (same axis and
        radius: conservative, at most the radius beyond each flat face), ``"exact"`` as an exact cylinder
        (the default, None, too).
        Objects come in the World's kind order; :meth:`column_names` names each column."""
        exact = self._exact(cylinders)
        dt = dtype or torch.get_default_dtype()
        by = {k: [p for p in self.objects if p.kind == k] for k in ("sphere", "cylinder", "box")}
        f = lambda rows, n: torch.tensor(rows, dtype=torch.float64, device="cpu").reshape(-1, n)  # noqa: E731
        spheres = f([[*p.pose[:3, 3].tolist(), p.dimensions[0]] for p in by["sphere"]], 4)
        cyl = []
        for p in by["cylinder"]:
            half = 0.5 * p.dimensions[0] * p.pose[:3, 2]
            c = p.pose[:3, 3]
            cyl.append([*(c - half).tolist(), *(c + half).tolist(), p.dimensions[1]])
        cyl_t = f(cyl, 7)
        boxes = by["box"]
        center = f([p.pose[:3, 3].tolist() for p in boxes], 3)
        rot = torch.stack([p.pose[:3, :3] for p in boxes]) if boxes else \
            torch.zeros(0, 3, 3, dtype=torch.float64, device="cpu")
        half = f([[0.5 * d for d in p.dimensions] for p in boxes], 3)
        cast = lambda t: t.to(dtype=dt, device=device)  # noqa: E731
        kw = {"cylinders": cast(cyl_t)} if exact else {"capsules": cast(cyl_t)}
        return World(spheres=cast(spheres), boxes=Box(cast(center), cast(rot), cast(half)), **kw)

    def column_names(self, cylinders: str | None = None) -> list[str]:
        """The name of every column of ``to_world(cylinders=cylinders)``'s world, in the World's order."""
        exact = self._exact(cylinders)
        kinds = ("sphere", "box", "cylinder") if exact else ("sphere", "cylinder", "box")
        return [p.name for k in kinds for p in self.objects if p.kind == k]

    @property
    def world_names(self) -> list[str]:
        """:meth:`column_names` of the default :meth:`to_world`."""
        return self.column_names()

    @staticmethod
    def _exact(cylinders: str | None) -> bool:
        if cylinders not in (None, "exact", "capsules"):
            raise ConventionError(f"expected cylinders as 'exact', 'capsules' or None, got {cylinders!r}")
        return cylinders != "capsules"  # exact by default; capsules: conservative, served by the C decisions


def is_moveit_scene(data) -> bool:
    """Whether a loaded YAML mapping is a MoveIt PlanningScene (it has ``world.collision_objects`` or an
    ``allowed_collision_matrix``) rather than a diffkin world file."""
    return isinstance(data, Mapping) and (
        (isinstance(data.get("world"), Mapping) and "collision_objects" in data["world"])
        or "allowed_collision_matrix" in data)


def read_scene(source) -> Scene:
    """A :class:`Scene` from a MoveIt PlanningScene YAML file (a path), its text, or its loaded mapping
    (module docstring). Errors (:class:`~diffkin.errors.ModelError`) name the file and the object, what was
    expected there and what came."""
    return scene_from_data(*_load(source))


def scene_from_data(where: str, data) -> Scene:
    """:func:`read_scene` of an already loaded mapping; ``where`` names it in errors."""
    if not is_moveit_scene(data):
        raise ModelError(f"{where}: not a MoveIt PlanningScene (expected world.collision_objects or an "
                         f"allowed_collision_matrix, got keys {_keys(data)})")
    world = data.get("world") or {}
    found = []
    for i, co in enumerate(world.get("collision_objects") or []):
        found += _object(co, f"{where}: world.collision_objects[{i}]")
    # every pose in one batched call: the object's pose times the primitive's
    T = _poses([f[2] for f in found]) @ _poses([f[3] for f in found])
    objects = [Primitive(name, kind, T[k], dims) for k, (name, kind, _, _, dims) in enumerate(found)]
    allowed, names = _acm(data.get("allowed_collision_matrix"), where)
    js = (data.get("robot_state") or {}).get("joint_state") or {}
    state = dict(zip(js.get("name") or [], map(float, js.get("position") or [])))
    return Scene(tuple(objects), allowed, names, state, str(data.get("name") or ""))


def _keys(data) -> str:
    return ", ".join(map(str, data)) if isinstance(data, Mapping) else type(data).__name__


def _load(source) -> tuple[str, object]:
    if isinstance(source, Mapping):
        return "scene", source
    import yaml

    try:
        loader = yaml.CSafeLoader
    except AttributeError:  # PyYAML without libyaml
        loader = yaml.SafeLoader
    if isinstance(source, (str, Path)) and "\n" not in str(source):
        path = Path(source)
        if not path.is_file():
            raise ModelError(f"scene file {str(path)!r} not found (expected an existing file, YAML text or a "
                             "mapping)")
        where, text = str(path), path.read_text(encoding="utf-8-sig")
    elif isinstance(source, str):
        where, text = "scene", source
    else:
        raise ModelError(f"expected a scene as a path, YAML text or a mapping, got {type(source).__name__}")
    try:
        return where, yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        raise ModelError(f"{where}: expected PlanningScene YAML, cannot read it: {exc}") from None


def _numbers(x, n: int | None, what: str) -> list[float]:
    try:
        out = [float(v) for v in x]
    except (TypeError, ValueError):
        raise ModelError(f"{what}: expected a list of numbers, got {x!r}") from None
    if n is not None and len(out) != n:
        raise ModelError(f"{what}: expected {n} numbers, got {len(out)}")
    if not all(abs(v) < float("inf") for v in out):
        raise ModelError(f"{what}: expected finite numbers, got {out}")
    return out


_IDENTITY = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]


def _pose(p, what: str) -> list[float]:
    """A geometry_msgs/Pose mapping -> ``[position (3), quaternion (w, x, y, z)]`` (missing parts: zero and
    the identity; the file's quaternion is (x, y, z, w))."""
    if p is None:
        return list(_IDENTITY)
    if not isinstance(p, Mapping):
        raise ModelError(f"{what}: expected a pose {{position, orientation}}, got {p!r}")
    out = list(_IDENTITY)
    if p.get("position") is not None:
        out[:3] = _numbers(p["position"], 3, f"{what}.position")
    if p.get("orientation") is not None:
        x, y, z, w = _numbers(p["orientation"], 4, f"{what}.orientation")
        if x * x + y * y + z * z + w * w < 1e-12:
            raise ModelError(f"{what}.orientation: expected a non-zero quaternion, got {[x, y, z, w]}")
        out[3:] = [w, x, y, z]
    return out


def _poses(rows: list[list[float]]) -> Tensor:
    """``(N, 4, 4)`` float64 homogeneous transforms of :func:`_pose` rows (quaternions normalised, (2.33))."""
    x = torch.tensor(rows, dtype=torch.float64, device="cpu").reshape(-1, 7)  # parsed on the host
    T = torch.eye(4, dtype=torch.float64, device="cpu").repeat(x.shape[0], 1, 1)
    T[:, :3, 3] = x[:, :3]
    if x.shape[0]:
        T[:, :3, :3] = quaternion_to_matrix(x[:, 3:])
    return T


def _object(co, what: str) -> list[tuple]:
    """(name, kind, object pose row, primitive pose row, dimensions) per primitive of a collision object."""
    if not isinstance(co, Mapping):
        raise ModelError(f"{what}: expected a collision object mapping, got {type(co).__name__}")
    name = str(co.get("id", ""))
    what = f"{what} ({name!r})"
    for key in ("meshes", "planes"):
        if co.get(key):
            raise ModelError(f"{what}: {key} are not supported (expected primitives: boxes, spheres and "
                             f"cylinders only, got {key})")
    if str(co.get("operation", "0")).lower() not in ("0", "add", "append"):
        raise ModelError(f"{what}: expected operation add (0) or append (only added objects are read), got "
                         f"{co['operation']!r}")
    prims, poses = co.get("primitives") or [], co.get("primitive_poses") or []
    if len(prims) != len(poses):
        raise ModelError(f"{what}: expected one primitive_pose per primitive, got {len(prims)} primitives "
                         f"and {len(poses)} primitive_poses")
    base = _pose(co.get("pose"), f"{what}.pose")
    out: list[tuple[str, str, list[float], list[float], tuple[float, ...]]] = []
    for k, (prim, pose) in enumerate(zip(prims, poses)):
        pw = f"{what}.primitives[{k}]"
        if not isinstance(prim, Mapping):
            raise ModelError(f"{pw}: expected {{type, dimensions}}, got {prim!r}")
        kind = prim.get("type")
        kind = _TYPES.get(kind, kind) if isinstance(kind, int) else str(kind).lower()
        if kind not in _DIMS:
            raise ModelError(f"{pw}: primitive type {prim.get('type')!r} is not supported (expected box, "
                             "sphere or cylinder)")
        dims = _numbers(prim.get("dimensions"), _DIMS[kind], f"{pw}.dimensions")
        if any(d < 0 for d in dims):
            raise ModelError(f"{pw}.dimensions: expected sizes >= 0, got {dims}")
        if kind == "cylinder" and dims[0] <= 0:  # without a height it has no axis (World refuses it too)
            raise ModelError(f"{pw}.dimensions: expected a cylinder height > 0, got {dims[0]}")
        out.append((name if len(prims) == 1 else f"{name}/{k}", kind, base,
                    _pose(pose, f"{what}.primitive_poses[{k}]"), tuple(dims)))
    return out


def _acm(acm, where: str) -> tuple[frozenset[frozenset[str]], tuple[str, ...]]:
    """The allowed pairs of an allowed-collision matrix: rows are lists of booleans or AllowedCollisionEntry
    mappings ``{enabled: [...]}``; the matrix must be symmetric; a true default entry (a name allowed to
    touch everything) is not supported."""
    what = f"{where}: allowed_collision_matrix"
    if acm is None:
        return frozenset(), ()
    if not isinstance(acm, Mapping):
        raise ModelError(f"{what}: expected a mapping, got {type(acm).__name__}")
    names = [str(n) for n in acm.get("entry_names") or []]
    rows = [r.get("enabled") if isinstance(r, Mapping) else r for r in acm.get("entry_values") or []]
    if len(rows) != len(names) or any(not isinstance(r, list) or len(r) != len(names) for r in rows):
        raise ModelError(f"{what}: expected entry_names (n names) and entry_values (n rows of n booleans), "
                         f"got {len(names)} names and rows of lengths "
                         f"{[len(r) if isinstance(r, list) else None for r in rows]}")
    if any(d is True for d in acm.get("default_entry_values") or []):
        raise ModelError(f"{what}: expected default_entry_values false, got true (a name allowed to touch "
                         "everything is not supported)")
    allowed = set()
    for i, row in enumerate(rows):
        for j, v in enumerate(row):
            if not isinstance(v, bool):
                raise ModelError(f"{what}.entry_values[{i}][{j}]: expected true or false, got {v!r}")
            if v != rows[j][i]:
                raise ModelError(f"{what}: expected a symmetric matrix, not symmetric: ({names[i]}, "
                                 f"{names[j]}) is {v} but ({names[j]}, {names[i]}) is {rows[j][i]}")
            if v and i < j:
                allowed.add(frozenset((names[i], names[j])))
    return frozenset(allowed), tuple(names)
