"""Collision geometry above the model: batched, differentiable signed distances (negative = penetration).

* :mod:`~diffkin.collision.distances`: spheres, capsules, points and half-spaces in closed form.
* :mod:`~diffkin.collision.boxes`: oriented boxes (:func:`box`) against all of those and each other.
* :mod:`~diffkin.collision.cylinders`: exact cylinders (flat ends) against all of those and each other.
* :mod:`~diffkin.collision.convex`: convex meshes (a vertex set's hull) against all of those and each other.
* :mod:`~diffkin.collision.pairs`: the pair table (kinds × kinds → distance, broad-phase bound, C entry).
* :func:`read_world` / :func:`read_scene`: world files and MoveIt PlanningScene YAML
  (:mod:`~diffkin.collision.moveit`).
* :class:`World`: the obstacles; :class:`RobotCollision`: the robot's geoms, its checked pairs,
  ``self_distances``, ``world_distances`` and ``min_distance``.

The exported distance functions check their input once (:mod:`diffkin.collision._checked`: shapes, dtypes,
broadcasting; typed errors); the kernels in ``distances`` / ``boxes`` themselves do not.

The model never imports this package (data flows ``model frames -> collision geometry -> distances``).
"""

from ._checked import box_box as box_box
from ._checked import box_convex as box_convex
from ._checked import box_cylinder as box_cylinder
from ._checked import box_halfspace as box_halfspace
from ._checked import capsule_box as capsule_box
from ._checked import capsule_capsule as capsule_capsule
from ._checked import capsule_capsule_pairs as capsule_capsule_pairs
from ._checked import capsule_convex as capsule_convex
from ._checked import capsule_cylinder as capsule_cylinder
from ._checked import capsule_halfspace as capsule_halfspace
from ._checked import convex_convex as convex_convex
from ._checked import convex_halfspace as convex_halfspace
from ._checked import cylinder_convex as cylinder_convex
from ._checked import cylinder_cylinder as cylinder_cylinder
from ._checked import cylinder_halfspace as cylinder_halfspace
from ._checked import point_box as point_box
from ._checked import point_cylinder as point_cylinder
from ._checked import point_segment_parameter as point_segment_parameter
from ._checked import segment_box as segment_box
from ._checked import segment_closest_parameters as segment_closest_parameters
from ._checked import sphere_box as sphere_box
from ._checked import sphere_capsule as sphere_capsule
from ._checked import sphere_cylinder as sphere_cylinder
from ._checked import sphere_halfspace as sphere_halfspace
from ._checked import sphere_sphere as sphere_sphere
from .boxes import Box as Box
from .boxes import box as box
from .moveit import Primitive as Primitive
from .moveit import Scene as Scene
from .moveit import read_scene as read_scene
from .robot import Geom as Geom
from .robot import RobotCollision as RobotCollision
from .world import World as World
from .world_file import read_world as read_world

__all__ = [
    "read_world",
    "read_scene",
    "Scene",
    "Primitive",
    "Box",
    "Geom",
    "RobotCollision",
    "World",
    "box",
    "box_box",
    "box_cylinder",
    "box_halfspace",
    "box_convex",
    "capsule_box",
    "capsule_capsule",
    "capsule_capsule_pairs",
    "capsule_cylinder",
    "capsule_convex",
    "convex_convex",
    "convex_halfspace",
    "cylinder_convex",
    "cylinder_cylinder",
    "cylinder_halfspace",
    "capsule_halfspace",
    "point_box",
    "point_cylinder",
    "point_segment_parameter",
    "segment_box",
    "segment_closest_parameters",
    "sphere_box",
    "sphere_capsule",
    "sphere_cylinder",
    "sphere_halfspace",
    "sphere_sphere",
]
