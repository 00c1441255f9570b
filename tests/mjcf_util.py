"""Compile a vendored MJCF model whose mesh, texture and height-field files are absent.

The MuJoCo Menagerie models under ``tests/data/mjcf`` are vendored as XML only (no meshes or
textures). ``mujoco.MjModel.from_xml_path`` refuses them ("Error opening file 'assets/link0.stl'").
Kinematics needs no asset file, so :func:`compile_without_assets` parses the XML with MuJoCo's own
parser (``<include>``, default classes, ``childclass``, ``<compiler angle/eulerseq>``, frames all
resolved by MuJoCo) and removes only what reads a file before compiling.
"""

from __future__ import annotations

from pathlib import Path

import mujoco

# Stand-in radius for a mesh / height-field geom: small, but positive, so that a body whose inertia
# MuJoCo infers from its geoms keeps a positive mass and the model still compiles.
_STAND_IN_RADIUS = 0.01


def _geoms_to_spheres(spec: mujoco.MjSpec) -> None:
    """Turn every mesh and height-field geom into a small sphere, keeping its name, body, pose and class.

    The geom is kept (not deleted) so that contact pairs, excludes and sensors that name it still
    resolve; body frames do not depend on geoms, so kinematics is unchanged.
    """
    file_types = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SDF)
    for geom in spec.geoms:
        if geom.type in file_types:
            geom.type = mujoco.mjtGeom.mjGEOM_SPHERE
            geom.meshname = ""
            geom.hfieldname = ""
            geom.size = [_STAND_IN_RADIUS, 0.0, 0.0]


def _drop_file_assets(spec: mujoco.MjSpec) -> None:
    """Delete meshes, height fields, skins and file textures; clear the texture slots of materials."""
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    for hfield in list(spec.hfields):
        spec.delete(hfield)
    for skin in list(spec.skins):
        spec.delete(skin)
    for texture in list(spec.textures):
        if texture.file or any(texture.cubefiles):
            spec.delete(texture)
    for material in spec.materials:
        material.textures = [""] * len(material.textures)


def compile_without_assets(path: str | Path) -> mujoco.MjModel:
    """Compile the MJCF file at ``path`` with MuJoCo, without the asset files it names.

    Recipe (works for every model in ``tests/data/mjcf/index.json``):

    1. ``mujoco.MjSpec.from_file(path)`` -- MuJoCo's own parser; ``<include file=...>`` is resolved
       relative to the file's directory, so pass the path, not the text.
    2. Every geom of type mesh / hfield / sdf becomes a sphere of radius 0.01 (same name, body, pose,
       class and mass settings), so references to it still resolve.
    3. All ``<mesh>``, ``<hfield>`` and ``<skin>`` assets and every ``<texture>`` with a ``file`` are
       deleted, and materials forget their textures.
    4. ``spec.compile()``.

    Body and site frames, joints (``nq``, ``nv``, types, axes, ``qpos0``), equality constraints and
    keyframes come out exactly as MuJoCo compiles the full model; only geom shapes and the inertia of
    bodies whose inertia MuJoCo infers from mesh geoms differ.

    Args:
        path: path of an MJCF file (its directory is used for ``<include>``).

    Returns:
        The compiled ``mujoco.MjModel``.
    """
    spec = mujoco.MjSpec.from_file(str(path))
    _geoms_to_spheres(spec)
    _drop_file_assets(spec)
    return spec.compile()
