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

from diffkin.models.mjcf import compile_mjcf


def compile_without_assets(path: str | Path) -> mujoco.MjModel:
    """The library's recipe (:func:`diffkin.models.mjcf.compile_mjcf`): mesh / height-field / SDF geoms
    become small spheres, file assets are dropped, then MuJoCo compiles the model."""
    return compile_mjcf(path)[0]


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
