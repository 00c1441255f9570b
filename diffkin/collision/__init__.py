"""Collision geometry above the model: batched, differentiable signed distances (negative = penetration).

* :mod:`~diffkin.collision.distances`: spheres, capsules, points and half-spaces in closed form.
* :mod:`~diffkin.collision.boxes`: oriented boxes (:func:`box`) against all of those and each other.
* :class:`World`: the obstacles; :class:`RobotCollision`: the robot's geoms, its checked pairs,
  ``self_distances``, ``world_distances`` and ``min_distance``.

The model never imports this package (data flows ``model frames -> collision geometry -> distances``).
"""

from .boxes import Box, box, box_box, box_halfspace, capsule_box, point_box, segment_box, sphere_box
from .distances import (
    capsule_capsule,
    capsule_capsule_pairs,
    capsule_halfspace,
    point_segment_parameter,
    segment_closest_parameters,
    sphere_capsule,
    sphere_halfspace,
    sphere_sphere,
)
from .robot import Geom, RobotCollision
from .world import World

__all__ = [
    "Box",
    "Geom",
    "RobotCollision",
    "World",
    "box",
    "box_box",
    "box_halfspace",
    "capsule_box",
    "capsule_capsule",
    "capsule_capsule_pairs",
    "capsule_halfspace",
    "point_box",
    "point_segment_parameter",
    "segment_box",
    "segment_closest_parameters",
    "sphere_box",
    "sphere_capsule",
    "sphere_halfspace",
    "sphere_sphere",
]
