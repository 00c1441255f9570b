"""URDF reading, validation and origin rewriting in pure Python (standard-library XML only).

:func:`parse_urdf` reads a URDF (path, XML text or bytes, with or without an XML encoding declaration) into a
:class:`URDFTree` of :class:`JointSpec` records: the kinematic skeleton only (links, joints, origins, axes,
limits, mimics); visuals, collisions, inertials, transmissions, gazebo and namespaced tags are ignored there
(:func:`parse_collisions` and :func:`parse_inertials` read the collision and inertial elements). It
validates the structure (unique names, existing links, one parent per link, exactly one root, no loops,
non-zero moving axes, ordered limits, acyclic mimics; a ``<mimic>`` on a fixed joint is inert, as in ROS)
and raises :class:`~diffkin.errors.ModelError` naming the offending joint or link. Every walk is iterative
with a visited set, so a malformed file never hangs.

:func:`write_urdf` writes new joint origins (e.g. calibrated ones) back by text surgery on the source: only
the ``<origin>`` element directly inside each named ``<joint>`` changes; comments, whitespace, attribute
order and every other element (including the ``<origin>`` of visuals, collisions and inertials) stay
byte-for-byte identical.

This is the project's only URDF text reader and writer; the model layers build on it.
"""

from __future__ import annotations

import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from ..errors import ModelError
from ..kernels.configuration import JOINT_KINDS, urdf_kind

__all__ = ["JointSpec", "URDFTree", "parse_urdf", "write_urdf", "joint_types", "moves",
           "CollisionSpec", "parse_collisions", "InertialSpec", "parse_inertials"]


def joint_types() -> tuple[str, ...]:
    """The URDF joint types read: ``"fixed"`` and the ``urdf`` names of the joint kinds table."""
    return ("fixed",) + tuple(k.urdf for k in JOINT_KINDS.values() if k.urdf)


def moves(jtype: str) -> bool:
    """Whether a URDF joint type moves (some joint kind reads it)."""
    return urdf_kind(jtype) is not None


Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class JointSpec:
    """One ``<joint>``: its type, links, fixed origin (from the parent link frame), axis, limits and mimic.

    ``axis`` is as written in the file (not normalised); ``lower``/``upper`` are ``None`` when absent (always
    for continuous joints); ``mimic`` is ``(leader joint, multiplier, offset)`` or ``None``; ``velocity`` the
    ``<limit velocity=>`` (rad/s or m/s) or ``None`` when absent.
    """

    name: str
    type: str
    parent: str
    child: str
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    axis: Vec3 = (1.0, 0.0, 0.0)
    lower: float | None = None
    upper: float | None = None
    mimic: tuple[str, float, float] | None = None
    velocity: float | None = None


@dataclass(frozen=True)
class URDFTree:
    """A validated kinematic tree: links and joints in file order, its unique root and the source text."""

    name: str
    links: tuple[str, ...]
    joints: tuple[JointSpec, ...]
    root: str
    text: str

    # Indices, built on first use (cached_property writes the instance __dict__, so frozen is fine).
    @cached_property
    def _by_name(self) -> dict[str, JointSpec]:
        return {j.name: j for j in self.joints}

    @cached_property
    def _by_child(self) -> dict[str, JointSpec]:
        return {j.child: j for j in self.joints}

    @cached_property
    def _by_parent(self) -> dict[str, list[JointSpec]]:
        out: dict[str, list[JointSpec]] = {link: [] for link in self.links}
        for j in self.joints:
            out.setdefault(j.parent, []).append(j)
        return out

    @cached_property
    def _link_set(self) -> frozenset[str]:
        return frozenset(self.links)

    def _check_link(self, link: str, role: str = "link") -> None:
        if link not in self._link_set:
            leaves = [k for k in self.links if not self._by_parent.get(k)]
            shown = ", ".join(leaves[:12]) + (", ..." if len(leaves) > 12 else "")
            raise ModelError(f"{role} {link!r} is not a link of URDF {self.name!r}; its leaf links: {shown}")

    def joint(self, name: str) -> JointSpec:
        """The joint called ``name`` (ModelError if there is none)."""
        try:
            return self._by_name[name]
        except KeyError:
            raise ModelError(f"joint {name!r} is not a joint of URDF {self.name!r}") from None

    def parent_joint(self, link: str) -> JointSpec | None:
        """The joint whose child is ``link``; ``None`` for the root."""
        self._check_link(link)
        return self._by_child.get(link)

    def children(self, link: str) -> list[JointSpec]:
        """The joints whose parent is ``link``, in file order."""
        self._check_link(link)
        return list(self._by_parent.get(link, ()))

    def path(self, end_link: str, root_link: str | None = None) -> list[JointSpec]:
        """Joints from ``root_link`` (default: the tree's root) down to ``end_link``, root side first."""
        self._check_link(end_link, "end link")
        if root_link is None:
            root_link = self.root
        self._check_link(root_link, "root link")
        out: list[JointSpec] = []
        link, seen = end_link, {end_link}
        while link != root_link:
            j = self._by_child.get(link)
            if j is None:
                raise ModelError(f"root link {root_link!r} is not an ancestor of end link {end_link!r}")
            out.append(j)
            link = j.parent
            if link in seen:  # only reachable for a hand-built, cyclic tree
                raise ModelError(f"kinematic loop through link {link!r} above {end_link!r}")
            seen.add(link)
        out.reverse()
        return out


# ----------------------------------------------------------------------------------------------- reading

_DECL = re.compile(r"\A\s*<\?xml\b[^>]*?\?>", re.S)
_ENCODING = re.compile(rb"""\A\s*<\?xml\b[^>]*?\bencoding\s*=\s*(["'])([A-Za-z0-9._-]+)\1""", re.S)


def _decode(data: bytes, origin: str) -> str:
    """Bytes to text: BOM first, then the XML declaration's encoding, default UTF-8."""
    if data.startswith(b"\xef\xbb\xbf"):
        encoding, data = "utf-8", data[3:]
    elif data.startswith((b"\xff\xfe", b"\xfe\xff")):
        encoding = "utf-16"
    else:
        m = _ENCODING.match(data)
        encoding = m.group(2).decode("ascii") if m else "utf-8"
    try:
        return data.decode(encoding)
    except LookupError:
        raise ModelError(f"URDF {origin}: unknown encoding {encoding!r} in the XML declaration") from None
    except UnicodeDecodeError as e:
        raise ModelError(f"URDF {origin}: not valid {encoding} text ({e})") from None


def _read(source) -> tuple[str, str]:
    """(text, a description of the source for messages)."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return _decode(bytes(source), "bytes"), "bytes"
    if isinstance(source, str) and "<" in source:
        return source.lstrip("\ufeff"), "text"
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.is_file():
            raise ModelError(f"{source}: no such URDF file (nor URDF XML text)")
        return _decode(path.read_bytes(), repr(str(path))), repr(str(path))
    raise ModelError(f"URDF source must be a path, XML text or bytes, got {type(source).__name__}")


def _parse_xml(text: str, origin: str) -> ET.Element:
    # ElementTree refuses a str with an encoding declaration; blank the declaration out (same length, same
    # newlines) so line and column numbers in errors still match the source.
    m = _DECL.match(text)
    if m:
        text = re.sub(r"[^\n]", " ", m.group(0)) + text[m.end():]
    try:
        return ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise ModelError(f"URDF {origin}: malformed XML at line {line}, column {col + 1}: {e}") from None


def _floats(value: str, n: int, where: str) -> tuple[float, ...]:
    parts = value.split()
    if len(parts) != n:
        raise ModelError(f"{where}: expected {n} number{'s' if n > 1 else ''}, got {value!r}")
    out = []
    for p in parts:
        try:
            if "_" in p:
                raise ValueError
            v = float(p)
        except ValueError:
            raise ModelError(f"{where}: {p!r} is not a number (in {value!r})") from None
        if not math.isfinite(v):
            raise ModelError(f"{where}: non-finite value {p!r} (in {value!r})")
        out.append(v)
    return tuple(out)


def _vec3(elem: ET.Element | None, attr: str, default: Vec3, where: str) -> Vec3:
    if elem is None or elem.get(attr) is None:
        return default
    return _floats(elem.get(attr), 3, f"{where} <{elem.tag} {attr}>")  # type: ignore[return-value]


def _opt_float(elem: ET.Element | None, attr: str, where: str) -> float | None:
    if elem is None or elem.get(attr) is None:
        return None
    return _floats(elem.get(attr), 1, f"{where} <{elem.tag} {attr}>")[0]


def _link_ref(elem: ET.Element, tag: str, where: str) -> str:
    sub = elem.find(tag)
    if sub is None or not sub.get("link"):
        raise ModelError(f"{where} has no <{tag} link=...>")
    return sub.get("link")  # type: ignore[return-value]


def _joint_spec(elem: ET.Element, index: int) -> JointSpec:
    name = elem.get("name")
    if not name:
        raise ModelError(f"joint #{index} (in file order) has no name")
    where = f"joint {name!r}"
    jtype = elem.get("type")
    if not jtype:
        raise ModelError(f"{where} has no type")
    kind = urdf_kind(jtype)
    if kind is None and jtype != "fixed":
        raise ModelError(f"{where}: unknown type {jtype!r} (one of {', '.join(joint_types())})")
    parent = _link_ref(elem, "parent", where)
    child = _link_ref(elem, "child", where)
    origin = elem.find("origin")
    xyz = _vec3(origin, "xyz", (0.0, 0.0, 0.0), where)
    rpy = _vec3(origin, "rpy", (0.0, 0.0, 0.0), where)
    axis = _vec3(elem.find("axis"), "xyz", (1.0, 0.0, 0.0), where)
    if kind is not None and kind.has_axis and not any(axis):
        raise ModelError(f"{where} ({jtype}) has a zero axis {axis}")
    limit = elem.find("limit")
    lower = _opt_float(limit, "lower", where)
    upper = _opt_float(limit, "upper", where)
    velocity = _opt_float(limit, "velocity", where)
    if kind is not None and not kind.limited:
        lower = upper = None
    if kind is not None and lower is not None and upper is not None and lower > upper:
        raise ModelError(f"{where}: limit lower {lower} > upper {upper}")
    mimic = None
    m = elem.find("mimic")
    if m is not None:
        leader = m.get("joint")
        if not leader:
            raise ModelError(f"{where}: <mimic> has no joint attribute")
        mult = _opt_float(m, "multiplier", where)
        off = _opt_float(m, "offset", where)
        mimic = (leader, 1.0 if mult is None else mult, 0.0 if off is None else off)
    return JointSpec(name, jtype, parent, child, xyz, rpy, axis, lower, upper, mimic,  # type: ignore[arg-type]
                     velocity)


def _cycle_from(start: str, parent_of: Mapping[str, str]) -> list[str]:
    """Follow parent pointers from ``start`` (each link has at most one) to the cycle it ends in."""
    order: dict[str, int] = {}
    node = start
    while node not in order:
        order[node] = len(order)
        node = parent_of[node]  # a link off the root's tree always has a parent (else it would be a root)
    cycle = [n for n, i in sorted(order.items(), key=lambda kv: kv[1]) if i >= order[node]]
    return cycle


def _validate(links: list[str], joints: list[JointSpec]) -> str:
    """Structural checks; returns the root link."""
    if not links:
        raise ModelError("URDF has no links")
    seen: set[str] = set()
    for link in links:
        if link in seen:
            raise ModelError(f"duplicate link name {link!r}")
        seen.add(link)
    by_name: dict[str, JointSpec] = {}
    for j in joints:
        if j.name in by_name:
            raise ModelError(f"duplicate joint name {j.name!r}")
        by_name[j.name] = j
    parent_joint: dict[str, JointSpec] = {}
    for j in joints:
        for role, link in (("parent", j.parent), ("child", j.child)):
            if link not in seen:
                raise ModelError(f"joint {j.name!r}: {role} link {link!r} does not exist")
        if j.child in parent_joint:
            raise ModelError(f"link {j.child!r} has two parent joints: {parent_joint[j.child].name!r} and "
                             f"{j.name!r}")
        parent_joint[j.child] = j

    roots = [link for link in links if link not in parent_joint]
    parent_of = {link: j.parent for link, j in parent_joint.items()}
    if len(roots) > 1:
        raise ModelError(f"URDF is not connected: {len(roots)} root links {roots} (a tree has exactly one)")
    if not roots:
        raise ModelError(f"kinematic loop (no root link) through links {_cycle_from(links[0], parent_of)}")
    root = roots[0]
    # Every link must hang below the root; one that does not sits on (or below) a cycle.
    kids: dict[str, list[str]] = {}
    for j in joints:
        kids.setdefault(j.parent, []).append(j.child)
    reached, stack = {root}, [root]
    while stack:
        for c in kids.get(stack.pop(), ()):
            if c not in reached:
                reached.add(c)
                stack.append(c)
    for link in links:
        if link not in reached:
            raise ModelError(f"kinematic loop through links {_cycle_from(link, parent_of)} "
                             f"(not reachable from the root {root!r})")

    # Mimics: the leader exists, is not fixed, and the leader pointers have no cycle. A <mimic> on a fixed
    # joint is inert (a fixed joint has nothing to follow; ROS ignores it, as VAMP's Panda fingers have it):
    # it is kept in the JointSpec but neither checked nor followed.
    for j in joints:
        if j.mimic is None or j.type == "fixed":
            continue
        leader = by_name.get(j.mimic[0])
        if leader is None:
            raise ModelError(f"joint {j.name!r} mimics {j.mimic[0]!r}, which is not a joint")
        if leader.type == "fixed":
            raise ModelError(f"joint {j.name!r} mimics {leader.name!r}, which is fixed")
    done: set[str] = set()
    for j in joints:
        walk: dict[str, int] = {}
        name: str | None = j.name
        while name is not None and name not in done and name not in walk:
            walk[name] = len(walk)
            spec = by_name[name]
            name = spec.mimic[0] if spec.mimic and spec.type != "fixed" else None
        if name is not None and name in walk:
            cycle = [n for n, i in walk.items() if i >= walk[name]]
            raise ModelError(f"mimic cycle among joints {cycle}")
        done.update(walk)
    return root


def parse_urdf(source) -> URDFTree:
    """Read and validate a URDF: ``source`` is a path (str or Path), XML text (str) or bytes.

    Raises ModelError (naming the joint or link, and starting with the file path when ``source`` is a path)
    on malformed XML or kinematics; see the module docstring.
    """
    is_path = isinstance(source, os.PathLike) or (isinstance(source, str) and "<" not in source)
    try:
        text, origin = _read(source)
        return _parse_text(text, origin)
    except ModelError as e:
        if not is_path or str(e).startswith(str(source)):
            raise
        msg = str(e).removeprefix(f"URDF {str(Path(source))!r}: ")
        raise ModelError(f"{Path(source)}: {msg}") from None


def _parse_text(text: str, origin: str) -> URDFTree:
    robot = _parse_xml(text, origin)
    if robot.tag != "robot":
        raise ModelError(f"URDF {origin}: the root element is <{robot.tag}>, not <robot>")
    links: list[str] = []
    for i, elem in enumerate(robot.findall("link")):
        name = elem.get("name")
        if not name:
            raise ModelError(f"link #{i} (in file order) has no name")
        links.append(name)
    joints = [_joint_spec(elem, i) for i, elem in enumerate(robot.findall("joint"))]
    root = _validate(links, joints)
    return URDFTree(robot.get("name", ""), tuple(links), tuple(joints), root, text)


# ----------------------------------------------------------------------------------------------- writing

_NAME = r"[^\s/>=<!?\"']+"
_ATTR = re.compile(rf"""({_NAME})\s*=\s*(?:"([^"]*)"|'([^']*)')""")
_START = re.compile(rf"""<({_NAME})((?:\s+{_NAME}\s*=\s*(?:"[^"]*"|'[^']*'))*)\s*(/?)>""")
_END = re.compile(rf"</({_NAME})\s*>")
_REF = re.compile(r"&(#x[0-9a-fA-F]+|#[0-9]+|lt|gt|amp|quot|apos);")
_ENTITIES = {"lt": "<", "gt": ">", "amp": "&", "quot": '"', "apos": "'"}


def _unescape(value: str) -> str:
    def sub(m: re.Match) -> str:
        ref = m.group(1)
        if ref.startswith("#x"):
            return chr(int(ref[2:], 16))
        if ref.startswith("#"):
            return chr(int(ref[1:]))
        return _ENTITIES[ref]

    return _REF.sub(sub, value)


@dataclass
class _JointSpan:
    start: re.Match  # the <joint ...> start tag
    end: int | None = None  # offset of its </joint> (None when self-closing)
    origin: re.Match | None = None  # its first direct <origin> child's start tag
    axis: re.Match | None = None  # its first direct <axis> child's start tag


def _joint_spans(text: str) -> dict[str, _JointSpan]:
    """The robot element's direct ``<joint>`` children, by name, found by a small tag scanner.

    Comments, CDATA, processing instructions and the DOCTYPE are skipped; only element depth matters, so a
    ``<joint>`` inside ``<transmission>`` or ``<gazebo>`` and an ``<origin>`` inside ``<visual>`` are ignored.
    """
    spans: dict[str, _JointSpan] = {}
    depth, pos, n = 0, 0, len(text)
    current: _JointSpan | None = None
    while True:
        pos = text.find("<", pos)
        if pos < 0 or pos >= n:
            break
        if text.startswith("<!--", pos):
            pos = _skip(text, pos, "-->")
        elif text.startswith("<![CDATA[", pos):
            pos = _skip(text, pos, "]]>")
        elif text.startswith("<?", pos):
            pos = _skip(text, pos, "?>")
        elif text.startswith("<!", pos):  # DOCTYPE, possibly with an internal subset
            close = text.find(">", pos)
            bracket = text.find("[", pos, close if close >= 0 else n)
            if bracket >= 0:
                close = text.find(">", text.find("]", bracket))
            pos = n if close < 0 else close + 1
        elif text.startswith("</", pos):
            m = _END.match(text, pos)
            if m is None:
                raise ModelError(f"write_urdf: malformed end tag at offset {pos} of the source text")
            depth -= 1
            if current is not None and depth == 1 and m.group(1) == "joint":
                current.end = m.start()
                current = None
            pos = m.end()
        else:
            m = _START.match(text, pos)
            if m is None:
                raise ModelError(f"write_urdf: malformed start tag at offset {pos} of the source text")
            tag, self_closing = m.group(1), bool(m.group(3))
            if depth == 1 and tag == "joint":
                attrs = {a.group(1): _unescape(a.group(2) if a.group(2) is not None else a.group(3))
                         for a in _ATTR.finditer(m.group(2))}
                span = _JointSpan(m)
                if "name" in attrs and attrs["name"] not in spans:
                    spans[attrs["name"]] = span
                current = None if self_closing else span
            elif depth == 2 and tag == "origin" and current is not None and current.origin is None:
                current.origin = m
            elif depth == 2 and tag == "axis" and current is not None and current.axis is None:
                current.axis = m
            if not self_closing:
                depth += 1
            pos = m.end()
    return spans


def _skip(text: str, pos: int, terminator: str) -> int:
    end = text.find(terminator, pos)
    return len(text) if end < 0 else end + len(terminator)


def _fmt(values, joint: str, what: str) -> str:
    try:
        vals = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ModelError(f"write_urdf: joint {joint!r} {what} must be 3 numbers, got {values!r}") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise ModelError(f"write_urdf: joint {joint!r} {what} must be 3 finite numbers, got {values!r}")
    return " ".join(repr(v) for v in vals)


def _set_attrs(tag: re.Match, new: dict[str, str]) -> str:
    """Start tag ``tag`` with attributes ``new`` set (values replaced in place, quotes kept, or appended)."""
    text, base = tag.group(0), tag.start()
    edits: list[tuple[int, int, str]] = []
    attrs_at = tag.start(2) - base
    last_end = attrs_at
    missing = dict(new)
    for a in _ATTR.finditer(tag.group(2)):
        name = a.group(1)
        last_end = attrs_at + a.end()
        if name in missing:
            g = 2 if a.group(2) is not None else 3
            edits.append((attrs_at + a.start(g), attrs_at + a.end(g), missing.pop(name)))
    if missing:
        edits.append((last_end, last_end, "".join(f' {k}="{v}"' for k, v in missing.items())))
    for s, e, v in sorted(edits, reverse=True):
        text = text[:s] + v + text[e:]
    return text


def write_urdf(tree: URDFTree, origins: Mapping[str, tuple[Sequence[float], Sequence[float]]],
               path=None, *, axes: Mapping[str, Sequence[float]] | None = None) -> str:
    """``tree.text`` with the ``<origin>`` of each joint in ``origins`` (name -> (xyz, rpy)) replaced, and
    the ``<axis>`` of each joint in ``axes`` (name -> xyz).

    Only those attributes change (an ``<origin/>`` or ``<axis/>`` is inserted as the joint's first child if
    it has none); everything else stays byte-for-byte. Numbers are written as Python's shortest round-trip
    repr, so ``parse_urdf`` of the result gives back exactly these floats. Writes to ``path`` as well when
    given (encoded per the text's XML declaration, default UTF-8). Returns the new text.
    """
    text = tree.text
    spans = _joint_spans(text)
    edits: list[tuple[int, int, str]] = []
    changes: list[tuple[str, str, dict[str, str]]] = []
    for name, value in origins.items():
        tree.joint(name)  # ModelError if unknown
        try:
            xyz, rpy = value
        except (TypeError, ValueError):
            raise ModelError(f"write_urdf: joint {name!r} origin must be (xyz, rpy), got {value!r}") from None
        changes.append((name, "origin", {"xyz": _fmt(xyz, name, "xyz"), "rpy": _fmt(rpy, name, "rpy")}))
    for name, value in (axes or {}).items():
        tree.joint(name)
        changes.append((name, "axis", {"xyz": _fmt(value, name, "axis")}))
    inserted: dict[str, list[str]] = {}
    for name, tag, attrs in changes:
        span = spans.get(name)
        if span is None:
            raise ModelError(f"write_urdf: joint {name!r} not found in the source text")
        child = getattr(span, tag)
        if child is not None:
            edits.append((child.start(), child.end(), _set_attrs(child, attrs)))
        else:
            inserted.setdefault(name, []).append(
                f"<{tag} " + " ".join(f'{k}="{v}"' for k, v in attrs.items()) + "/>")
    for name, elements in inserted.items():
        start = spans[name].start
        if spans[name].end is None:  # self-closing <joint .../>: expand it
            body = start.group(0)[:start.end(2) - start.start()] + ">"
            edits.append((start.start(), start.end(), f"{body}{''.join(elements)}</joint>"))
        else:  # first children, indented like the joint's next line
            ws = re.match(r"[ \t]*\r?\n[ \t]*|[ \t]*", text[start.end():]).group(0)
            lead = ws if "\n" in ws else ""
            edits.append((start.end(), start.end(), "".join(lead + e for e in elements)))
    for s, e, v in sorted(edits, reverse=True):
        text = text[:s] + v + text[e:]
    if path is not None:
        m = _ENCODING.match(text.encode("ascii", "replace"))
        encoding = m.group(2).decode("ascii") if m else "utf-8"
        Path(path).write_bytes(text.encode(encoding))
    return text


# -------------------------------------------------------------------------------------- collision elements

@dataclass(frozen=True)
class CollisionSpec:
    """One ``<collision>`` of a link: its geometry in the link frame, as written in the file.

    ``type`` is ``sphere`` / ``cylinder`` / ``capsule`` / ``box`` / ``mesh``; ``size`` holds
    ``(radius,)``, ``(radius, length)``, ``(radius, length)``, ``(x, y, z)`` (full side lengths) or the
    mesh ``scale``; ``filename`` is the mesh's file name as written (else None); ``xyz`` / ``rpy`` its
    ``<origin>``; ``name`` its ``name`` attribute or ``"<link>/<i>"`` (i: the element's index in the link).
    """

    link: str
    name: str
    type: str
    size: tuple[float, ...]
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    filename: str | None = None


_GEOMETRY_ATTRS = {"sphere": ("radius",), "cylinder": ("radius", "length"), "capsule": ("radius", "length")}


def _collision_spec(link: str, i: int, elem: ET.Element) -> CollisionSpec | None:
    name = elem.get("name") or f"{link}/{i}"
    where = f"link {link!r} <collision> {name!r}"
    geometry = elem.find("geometry")
    shapes = [] if geometry is None else list(geometry)
    if not shapes:
        raise ModelError(f"{where} has no <geometry> shape")
    if len(shapes) > 1:  # URDF's <geometry> holds exactly one shape; taking one would drop the other silently
        raise ModelError(f"{where}: <geometry> holds {len(shapes)} shapes ("
                         f"{', '.join(f'<{s.tag}>' for s in shapes)}); URDF allows one: give each shape its "
                         "own <collision>")
    shape = shapes[0]
    origin = elem.find("origin")
    xyz = _vec3(origin, "xyz", (0.0, 0.0, 0.0), where)
    rpy = _vec3(origin, "rpy", (0.0, 0.0, 0.0), where)
    if shape.tag in _GEOMETRY_ATTRS:
        size = []
        for attr in _GEOMETRY_ATTRS[shape.tag]:
            v = _opt_float(shape, attr, where)
            if v is None or v < 0:
                raise ModelError(f"{where}: <{shape.tag}> needs {attr} >= 0, got {shape.get(attr)!r}")
            size.append(v)
        return CollisionSpec(link, name, shape.tag, tuple(size), xyz, rpy)
    if shape.tag == "box":
        size = _vec3(shape, "size", None, where)  # type: ignore[arg-type]
        if size is None or min(size) < 0:
            raise ModelError(f"{where}: <box> needs size with three numbers >= 0, got {shape.get('size')!r}")
        return CollisionSpec(link, name, "box", size, xyz, rpy)
    if shape.tag == "mesh":
        if not shape.get("filename"):
            raise ModelError(f"{where}: <mesh> has no filename")
        scale = _vec3(shape, "scale", (1.0, 1.0, 1.0), where)
        return CollisionSpec(link, name, "mesh", scale, xyz, rpy, shape.get("filename"))
    return None  # an unknown shape tag: not a collision primitive URDF defines


def parse_collisions(source, *, unknown: list[str] | None = None) -> dict[str, list[CollisionSpec]]:
    """The ``<collision>`` elements of every link, in file order: ``{link: [CollisionSpec, ...]}`` (links
    without collisions map to ``[]``). ``source`` as for :func:`parse_urdf` (or a :class:`URDFTree`).
    Shapes other than sphere, cylinder, capsule, box and mesh (``<cone>``, a typo) are left out: named in
    ``unknown`` (``"<name> (<tag>) on link <link>"``) when a list is given, else in one warning. ModelError
    on a malformed element (missing size, negative radius, mesh without file name, a ``<geometry>`` with
    more than one shape).
    """
    text, origin = (source.text, "tree") if isinstance(source, URDFTree) else _read(source)
    robot = _parse_xml(text, origin)
    out: dict[str, list[CollisionSpec]] = {}
    left_out: list[str] = []
    for elem in robot.findall("link"):
        link = elem.get("name", "")
        out[link] = []
        for i, c in enumerate(elem.findall("collision")):
            spec = _collision_spec(link, i, c)
            if spec is None:
                left_out.append(f"{c.get('name') or f'{link}/{i}'} (<{c.find('geometry')[0].tag}>) on link "
                                f"{link!r}")
            else:
                out[link].append(spec)
    if unknown is not None:
        unknown.extend(left_out)
    elif left_out:
        warnings.warn(f"URDF {origin}: {len(left_out)} <collision> shape(s) URDF does not define (box, "
                      f"cylinder, sphere, mesh; capsule) left out: {', '.join(left_out)}", stacklevel=2)
    return out


# --------------------------------------------------------------------------------------- inertial elements

@dataclass(frozen=True)
class InertialSpec:
    """The ``<inertial>`` of a link: ``mass`` (kg, >= 0), the inertial frame ``xyz`` / ``rpy`` (its
    ``<origin>``, in the link frame: ``xyz`` is the centre of mass) and the inertia tensor's six entries
    ``(ixx, ixy, ixz, iyy, iyz, izz)`` about the centre of mass in that frame (zeros where absent)."""

    link: str
    mass: float
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0,) * 6


def _inertial_spec(link: str, elem: ET.Element) -> InertialSpec:
    where = f"link {link!r} <inertial>"
    mass = _opt_float(elem.find("mass"), "value", where)
    if mass is None or mass < 0:
        raise ModelError(f"{where}: needs <mass value=...> >= 0, got "
                         f"{None if elem.find('mass') is None else elem.find('mass').get('value')!r}")
    origin = elem.find("origin")
    xyz = _vec3(origin, "xyz", (0.0, 0.0, 0.0), where)
    rpy = _vec3(origin, "rpy", (0.0, 0.0, 0.0), where)
    tensor = elem.find("inertia")
    inertia = tuple(_opt_float(tensor, k, where) or 0.0 for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"))
    return InertialSpec(link, mass, xyz, rpy, inertia)  # type: ignore[arg-type]


def parse_inertials(source) -> dict[str, InertialSpec]:
    """The ``<inertial>`` of every link that has one: ``{link: InertialSpec}`` (links without one are
    massless, as in URDF). ``source`` as for :func:`parse_urdf` (or a :class:`URDFTree`). ModelError on a
    malformed element (no mass, a negative mass, a non-number)."""
    text, origin = (source.text, "tree") if isinstance(source, URDFTree) else _read(source)
    robot = _parse_xml(text, origin)
    out: dict[str, InertialSpec] = {}
    for elem in robot.findall("link"):
        inertial = elem.find("inertial")
        if inertial is not None:
            link = elem.get("name", "")
            out[link] = _inertial_spec(link, inertial)
    return out
