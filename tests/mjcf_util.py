"""Compile a vendored MJCF model whose mesh, texture and height-field files are absent.

The MuJoCo Menagerie models under ``tests/data/mjcf`` are vendored as XML only (no meshes or
textures). ``mujoco.MjModel.from_xml_path`` refuses them ("Error opening file 'assets/link0.stl'").
Kinematics needs no asset file, so :func:`compile_without_assets` parses the XML with MuJoCo's own
parser (``<include>``, default classes, ``childclass``, ``<compiler angle/eulerseq>``, frames all
resolved by MuJoCo) and removes only what reads a file before compiling.
"""

from __future__ import annotations

import struct
import zlib
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


def _png_1x1() -> bytes:
    """A valid 1x1 white RGB PNG (stand-in for texture and height-field files)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\x00\xff\xff\xff"))
            + chunk(b"IEND", b""))


_TETRA_OBJ = b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _tetra_stl() -> bytes:
    """A binary STL of the same tetrahedron as ``_TETRA_OBJ``."""
    v = [(0, 0, 0), (0.1, 0, 0), (0, 0.1, 0), (0, 0, 0.1)]
    faces = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
    out = b"\0" * 80 + struct.pack("<I", len(faces))
    for face in faces:
        out += struct.pack("<3f", 0, 0, 0) + b"".join(struct.pack("<3f", *v[i]) for i in face) + b"\0\0"
    return out


def compile_with_stand_in_assets(path: str | Path) -> mujoco.MjModel:
    """Compile the MJCF file at ``path`` untouched, serving every asset file it names from memory.

    A second, independent way to get a model without the mesh files: the XML is not edited at all;
    each ``<mesh file>`` is served as a small tetrahedron (OBJ or binary STL by extension) and each
    ``<texture file>`` / ``<hfield file>`` as a 1x1 PNG, through MuJoCo's in-memory asset dictionary
    (looked up by the file name as written in the XML). Body and site frames do not depend on mesh
    content, so this model and :func:`compile_without_assets` must agree on them -- the tests use that
    to check the recipe.
    """
    spec = mujoco.MjSpec.from_file(str(path))
    assets: dict[str, bytes] = {}
    for mesh in spec.meshes:
        if mesh.file:
            assets[mesh.file] = _tetra_stl() if mesh.file.lower().endswith(".stl") else _TETRA_OBJ
    for item in list(spec.textures) + list(spec.hfields):
        if item.file:
            assets[item.file] = _png_1x1()
    return mujoco.MjModel.from_xml_path(str(path), assets)
