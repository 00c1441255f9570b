"""World files: obstacles for ``diffkin ik / fk --world FILE`` as YAML or JSON (format in docs/collision.md).

::

    # metres, in the robot's base frame
    spheres:    [[0.5, 0.0, 0.4, 0.1]]              # x, y, z, radius
    capsules:   [[0.3, -0.3, 0.2, 0.3, 0.3, 0.2, 0.04]]   # end point a, end point b, radius
    boxes:                                          # centre, half extents, optional rpy (URDF order)
      - {center: [0.4, 0.0, 0.05], half_extents: [0.1, 0.2, 0.05], rpy: [0, 0, 0.3]}
    halfspaces: [[0, 0, 1, -0.01]]                  # unit normal n, offset d: the solid {x : n·x <= d}
    points:     [[0.3, 0.1, 0.7]]
    cylinders:  [[0.6, 0.2, 0.0, 0.6, 0.2, 0.3, 0.05]]   # axis end points a, b (flat-face centres), radius

Every key is optional; an unknown key is an error naming the valid ones. A MoveIt PlanningScene YAML (a
``world: collision_objects:`` list and an ``allowed_collision_matrix``) is read as such
(:mod:`diffkin.collision.moveit`; its allowed pairs: :func:`~diffkin.collision.moveit.read_scene`).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
import yaml

from ..errors import DiffkinError, ModelError
from .boxes import box
from .moveit import is_moveit_scene, scene_from_data
from .world import World

__all__ = ["read_world", "WORLD_KEYS"]

#: the keys of a world file, in the order of ``world_distances``' last axis
WORLD_KEYS = ("spheres", "capsules", "boxes", "halfspaces", "points", "cylinders")
_BOX_KEYS = ("center", "half_extents", "rpy")


def read_world(path, *, dtype: torch.dtype | None = None, device=None) -> World:
    """A :class:`~diffkin.collision.World` from a ``.yaml`` / ``.yml`` / ``.json`` file (module docstring) or
    a MoveIt PlanningScene YAML (boxes, spheres, cylinders: :meth:`~diffkin.collision.moveit.Scene.to_world`),
    its tensors in ``dtype`` on ``device``. Errors name the file and the entry: the file's layout a
    :class:`~diffkin.errors.ModelError`, its values the :class:`World`'s (:class:`~diffkin.errors.ShapeError`,
    :class:`~diffkin.errors.NonFiniteError`, :class:`~diffkin.errors.ModelError`)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"world file {str(path)!r} not found (expected an existing .yaml / .json file)")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ModelError(f"{path}: expected a YAML / JSON world file (UTF-8 text), got byte "
                         f"0x{data[exc.start]:02x} at offset {exc.start}") from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ModelError(f"{path}: expected YAML / JSON, cannot read the world file: {exc}") from None
    if data is None:
        data = {}
    if is_moveit_scene(data):  # a MoveIt PlanningScene (diffkin.collision.moveit)
        return scene_from_data(str(path), data).to_world(dtype=dtype, device=device)
    if not isinstance(data, dict):
        raise ModelError(f"{path}: expected a mapping with keys {', '.join(WORLD_KEYS)}, got "
                         f"{type(data).__name__}")
    unknown = sorted(set(data) - set(WORLD_KEYS))
    if unknown:
        raise ModelError(f"{path}: unknown key(s) {', '.join(map(str, unknown))}; expected keys among "
                         f"{', '.join(WORLD_KEYS)}")
    boxes = _boxes(path, data.get("boxes"), dtype, device)
    lists = {k: data.get(k) or None for k in ("spheres", "capsules", "halfspaces", "points", "cylinders")}
    try:
        return World(boxes=boxes, dtype=dtype, device=device, **lists)
    except DiffkinError as exc:
        raise type(exc)(f"{path}: {exc}") from None


def _boxes(path: Path, entries, dtype, device):
    if not entries:
        return None
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ModelError(f"{path}: expected boxes as a list of {{center, half_extents, rpy}} mappings, got "
                         f"{entries!r:.80}")
    for i, e in enumerate(entries):
        bad = sorted(set(e) - set(_BOX_KEYS))
        if bad or "center" not in e or "half_extents" not in e:
            raise ModelError(f"{path}: boxes[{i}]: expected keys center, half_extents (and optional rpy), "
                             f"got {', '.join(map(str, e))}")
    rpy = [e.get("rpy", [0.0, 0.0, 0.0]) for e in entries]
    try:
        return box([e["center"] for e in entries], [e["half_extents"] for e in entries], rpy, dtype=dtype,
                   device=device)
    except DiffkinError as exc:
        raise type(exc)(f"{path}: boxes: {exc}") from None
