"""diffkin.models.urdf_xml: parsing the real URDFs, structural validation, origin rewriting, tree paths.

The real files are the vendored copies in ``tests/data/urdf`` (see its README.md), so every clone runs them.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from diffkin.errors import ModelError
from diffkin.models.urdf_xml import JointSpec, URDFTree, parse_urdf, write_urdf

DATA = Path(__file__).resolve().parent / "data" / "urdf"  # vendored real URDFs (tests/data/urdf/README.md)
REAL = sorted(DATA.glob("*.urdf"))
DECLARED = ["kinova", "meca500", "so101", "ur3_robot"]  # start with <?xml ... encoding="utf-8"?>


def real(name: str) -> Path:
    path = DATA / f"{name}.urdf"
    assert path.is_file(), f"{path} missing from the vendored URDFs"
    return path


# ------------------------------------------------------------------------------------------- real files

@pytest.mark.parametrize("path", REAL, ids=[p.stem for p in REAL])
def test_real_file_counts_and_root(path):
    tree = parse_urdf(path)
    robot = ET.parse(path).getroot()  # independent parse: direct link/joint children of <robot>
    assert len(tree.links) == len(robot.findall("link"))
    assert len(tree.joints) == len(robot.findall("joint"))
    assert tree.name == robot.get("name")
    roots = [link for link in tree.links if tree.parent_joint(link) is None]
    assert roots == [tree.root]
    assert all(tree.path(link)[-1].child == link for link in tree.links if link != tree.root)


@pytest.mark.parametrize("name", DECLARED)
def test_encoding_declaration_path_bytes_str(name):
    path = real(name)
    data = path.read_bytes()
    assert re.match(rb'<\?xml[^>]*encoding="utf-8"', data)
    from_path = parse_urdf(path)
    assert parse_urdf(str(path)) == from_path
    assert parse_urdf(data) == from_path
    assert parse_urdf(data.decode("utf-8")) == from_path
    assert from_path.text == data.decode("utf-8")


def test_encoding_declaration_latin1_bytes():
    text = ('<?xml version="1.0" encoding="ISO-8859-1"?>\n<robot name="caf\u00e9"><link name="b\u00e4se"/>'
            '<link name="a"/><joint name="j" type="fixed"><parent link="b\u00e4se"/><child link="a"/></joint>'
            "</robot>")
    tree = parse_urdf(text.encode("latin-1"))
    assert tree.name == "caf\u00e9" and tree.root == "b\u00e4se"
    assert parse_urdf(text) == tree  # the same, as a str with the declaration


def test_mimic_yumi():
    tree = parse_urdf(real("yumi"))
    # <mimic joint="gripper_r_joint"/>: multiplier and offset take their defaults
    j = tree.joint("gripper_r_joint_m")
    assert j.mimic == ("gripper_r_joint", 1.0, 0.0)
    assert (j.type, j.axis, j.lower, j.upper) == ("prismatic", (-1.0, 0.0, 0.0), 0.0, 0.025)
    assert j.rpy == (0.0, 0.0, 3.14159265359) and j.xyz == (0.0, 0.0065, 0.0837)


def test_mimic_talos():
    tree = parse_urdf(real("talos_reduced"))
    # <mimic joint="gripper_left_joint" multiplier="-1.0" offset="0.0"/> on a joint the reduced model fixed
    j = tree.joint("gripper_left_fingertip_1_joint")
    assert j.mimic == ("gripper_left_joint", -1.0, 0.0)
    assert j.type == "fixed"
    assert tree.joint("gripper_left_inner_double_joint").mimic == ("gripper_left_joint", 1.0, 0.0)
    assert tree.joint("gripper_left_joint").type == "revolute"


# ------------------------------------------------------------------------------------------ small trees

def urdf(body: str, name: str = "t") -> str:
    return f'<robot name="{name}">{body}</robot>'


def links(*names: str) -> str:
    return "".join(f'<link name="{n}"/>' for n in names)


def joint(name, parent, child, jtype="revolute", extra='<axis xyz="0 0 1"/>') -> str:
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>{extra}'
            "</joint>")


CHAIN = urdf(links("a", "b", "c", "d") + joint("j1", "a", "b") + joint("j2", "b", "c")
             + joint("j3", "b", "d"))


def test_small_tree_defaults_and_queries():
    body = (links("base", "l1", "l2")
            + '<joint name="j1" type="continuous"><parent link="base"/><child link="l1"/>'
              '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
            + '<joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/>'
              '<origin xyz="1\t2\n 3"/><axis xyz="0 0 2"/><limit upper="0.5"/>'
              '<visual><origin xyz="9 9 9"/></visual></joint>')
    tree = parse_urdf(urdf(body, "toy"))
    j1, j2 = tree.joints
    zero = (0.0, 0.0, 0.0)
    assert j1 == JointSpec("j1", "continuous", "base", "l1", zero, zero, (1.0, 0.0, 0.0), None, None, None,
                           1.0)  # a continuous joint keeps its velocity limit
    assert (j2.xyz, j2.rpy, j2.axis) == ((1.0, 2.0, 3.0), zero, (0.0, 0.0, 2.0))
    assert (j2.lower, j2.upper) == (None, 0.5)
    assert tree.name == "toy" and tree.root == "base" and tree.links == ("base", "l1", "l2")
    assert tree.parent_joint("base") is None and tree.parent_joint("l2") is j2
    assert tree.children("base") == [j1] and tree.children("l2") == []
    assert tree.path("l2") == [j1, j2] and tree.path("l2", "l1") == [j2] and tree.path("l1", "l1") == []
    with pytest.raises(ModelError, match="nope"):
        tree.joint("nope")
    with pytest.raises(ModelError, match="nope"):
        tree.children("nope")


def test_single_link_and_ignored_elements():
    text = ('<?xml version="1.0"?>\n<!-- c --><robot name="one" xmlns:xacro="http://ros.org/wiki/xacro">'
            '<material name="m"/><link name="only"><visual><origin xyz="1 2 3"/></visual></link>'
            '<xacro:property name="x" value="1"/><gazebo><joint>nothing</joint></gazebo>'
            '<transmission name="t"><joint name="ghost"/></transmission></robot>')
    tree = parse_urdf(text)
    assert tree.links == ("only",) and tree.joints == () and tree.root == "only"


@pytest.mark.parametrize(
    "text, names",
    [
        ("<robot><link name='a'/>", ["line 1"]),  # malformed XML
        ("<model name='x'><link name='a'/></model>", ["<model>"]),  # no <robot> root
        (urdf(links("a", "b") + '<joint type="fixed"><parent link="a"/><child link="b"/></joint>'),
         ["joint #0"]),
        (urdf(links("a", "b") + '<joint name="j"><parent link="a"/><child link="b"/></joint>'),
         ["'j'", "type"]),
        (urdf(links("a", "b") + '<joint name="j" type="fixed"><child link="b"/></joint>'), ["'j'", "parent"]),
        (urdf(links("a", "b") + '<joint name="j" type="fixed"><parent link="a"/></joint>'), ["'j'", "child"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "hinge")), ["'j'", "hinge"]),  # unknown type
        (urdf(links("a", "b", "a") + joint("j", "a", "b")), ["'a'", "duplicate link"]),
        (urdf(links("a", "b", "c") + joint("j", "a", "b") + joint("j", "b", "c")),
         ["'j'", "duplicate joint"]),
        (urdf(links("a", "b") + joint("j", "a", "ghost")), ["'j'", "'ghost'"]),  # missing child link
        (urdf(links("a", "b") + joint("j", "ghost", "b")), ["'j'", "'ghost'"]),  # missing parent link
        (urdf(links("a", "b", "c") + joint("j1", "a", "c") + joint("j2", "b", "c")), ["'c'", "'j1'", "'j2'"]),
        (urdf(links("a", "b", "c", "d") + joint("j1", "a", "b") + joint("j2", "c", "d")),
         ["'a'", "'c'", "root"]),  # disconnected
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<axis xyz="0 0 0"/>')), ["'j'", "axis"]),
        (urdf(links("a", "b")
              + joint("j", "a", "b", "prismatic", '<axis xyz="0 0 1"/><limit lower="1" upper="0"/>')),
         ["'j'", "lower"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<origin xyz="0 nan 0"/>')), ["'j'", "xyz"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<origin rpy="0 0"/>')), ["'j'", "rpy"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<axis xyz="0 0 inf"/>')), ["'j'", "axis"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<axis xyz="0 0 1"/><limit upper="1 2"/>')),
         ["'j'", "upper"]),
        (urdf(links("a", "b") + joint("j", "a", "b", "revolute", '<origin xyz="0 x 0"/>')), ["'j'", "xyz"]),
        (urdf(links("a", "b") + joint("j", "a", "b", extra='<axis xyz="1 0 0"/><mimic joint="k"/>')),
         ["'j'", "'k'"]),  # mimic leader missing
        (urdf(links("a", "b", "c") + joint("f", "a", "b", "fixed", "")
              + joint("j", "b", "c", extra='<axis xyz="1 0 0"/><mimic joint="f"/>')),
         ["'j'", "'f'", "fixed"]),
        (urdf(links("a", "b", "c") + joint("j1", "a", "b", extra='<axis xyz="1 0 0"/><mimic joint="j2"/>')
              + joint("j2", "b", "c", extra='<axis xyz="1 0 0"/><mimic joint="j1"/>')),
         ["'j1'", "'j2'", "mimic"]),
        (urdf(links("a", "b") + joint("j", "a", "b", extra='<axis xyz="1 0 0"/><mimic joint="j"/>')),
         ["'j'", "mimic"]),  # mimics itself
        ("<robot><link/></robot>", ["link #0"]),
    ],
    ids=["malformed", "not-robot", "joint-no-name", "no-type", "no-parent", "no-child", "unknown-type",
         "dup-link", "dup-joint", "missing-child", "missing-parent", "two-parents", "disconnected",
         "zero-axis", "lower-gt-upper", "nan", "rpy-count", "inf-axis", "limit-count", "not-a-number",
         "mimic-missing", "mimic-fixed", "mimic-cycle", "mimic-self", "link-no-name"],
)
def test_structural_errors(text, names):
    with pytest.raises(ModelError) as e:
        parse_urdf(text)
    for n in names:
        assert n in str(e.value), (n, str(e.value))


def test_malformed_xml_reports_line():
    with pytest.raises(ModelError, match="line 3"):
        parse_urdf('<?xml version="1.0" encoding="utf-8"?>\n<robot name="x">\n<link name="a"></robot>')


def test_loop_without_root_terminates():
    text = urdf(links("a", "b", "c") + joint("j1", "a", "b") + joint("j2", "b", "c") + joint("j3", "c", "a"))
    with pytest.raises(ModelError, match="loop") as e:
        parse_urdf(text)
    assert all(f"'{n}'" in str(e.value) for n in "abc")


def test_loop_beside_a_root_terminates():
    # r is the only root; b <-> c form a cycle that hangs off nothing, and d hangs off the cycle.
    text = urdf(links("r", "a", "b", "c", "d") + joint("j0", "r", "a") + joint("j1", "b", "c")
                + joint("j2", "c", "b") + joint("j3", "c", "d"))
    with pytest.raises(ModelError, match="loop") as e:
        parse_urdf(text)
    assert "'b'" in str(e.value) and "'c'" in str(e.value)


def test_self_loop_and_long_mimic_chain():
    with pytest.raises(ModelError, match="'a'"):
        parse_urdf(urdf(links("r", "a") + joint("j0", "r", "r")))
    n = 2000  # a long mimic chain j_i -> j_{i-1} is fine, and linear-time
    body = links(*[f"l{i}" for i in range(n + 1)]) + joint("j0", "l0", "l1")
    body += "".join(
        joint(f"j{i}", f"l{i}", f"l{i + 1}", extra=f'<axis xyz="1 0 0"/><mimic joint="j{i - 1}"/>')
        for i in range(1, n))
    tree = parse_urdf(urdf(body))
    assert tree.joint(f"j{n - 1}").mimic == (f"j{n - 2}", 1.0, 0.0)
    assert len(tree.path(f"l{n}")) == n


def test_source_errors(tmp_path):
    with pytest.raises(ModelError, match="no_such_file"):
        parse_urdf(tmp_path / "no_such_file.urdf")
    with pytest.raises(ModelError):
        parse_urdf(42)


# ---------------------------------------------------------------------------------------------- paths

def test_path_fr3():
    tree = parse_urdf(real("fr3"))
    path = tree.path("fr3_link8")  # the flange
    assert [j.name for j in path] == [f"fr3_joint{i}" for i in range(1, 9)]
    assert path[0].parent == tree.root == "fr3_link0"
    assert [j.type for j in path] == ["revolute"] * 7 + ["fixed"]
    assert all(a.child == b.parent for a, b in zip(path, path[1:]))
    assert [j.name for j in tree.path("fr3_link8", "fr3_link5")] == ["fr3_joint6", "fr3_joint7", "fr3_joint8"]


def test_path_baxter_both_arms():
    tree = parse_urdf(real("baxter"))
    for side in ("left", "right"):
        path = tree.path(f"{side}_gripper")
        names = [j.name for j in path]
        assert names[0] == "torso_t0" and names[-1] == f"{side}_endpoint"
        moving = [j.name for j in path if j.type != "fixed"]
        assert moving == [f"{side}_{s}" for s in ("s0", "s1", "e0", "e1", "w0", "w1", "w2")]
        assert all(a.child == b.parent for a, b in zip(path, path[1:]))


def test_path_errors():
    tree = parse_urdf(CHAIN)
    with pytest.raises(ModelError, match="'zz'"):
        tree.path("zz")
    with pytest.raises(ModelError, match="'zz'"):
        tree.path("c", "zz")
    with pytest.raises(ModelError, match="'d'.*not an ancestor.*'c'"):
        tree.path("c", "d")  # a sibling branch
    with pytest.raises(ModelError, match="'c'.*not an ancestor.*'b'"):
        tree.path("b", "c")  # below, not above


# ---------------------------------------------------------------------------------------------- writing

def _perturb(tree: URDFTree, names) -> dict:
    out = {}
    for k, name in enumerate(names):
        j = tree.joint(name)
        out[name] = (tuple(v + 0.1 * (k + 1) / 3 for v in j.xyz), tuple(v - 1e-7 * (k + 1) for v in j.rpy))
    return out


def _strip_joint_origins(text: str) -> str:
    """The text with each direct <origin .../> of a top-level joint blanked (for comparing the rest)."""
    return re.sub(r"(<joint\b[^>]*[^/]>\s*(?:<[^o!][^>]*>\s*|<!--.*?-->\s*)*)<origin\b[^>]*>", r"\1<origin/>",
                  text, flags=re.S)


@pytest.mark.parametrize("name", ["fr3", "baxter", "ur3_robot"])
def test_write_round_trip_real(name, tmp_path):
    path = real(name)
    tree = parse_urdf(path)
    names = [j.name for j in tree.joints][::3]
    origins = _perturb(tree, names)
    out = tmp_path / f"{name}.urdf"
    text = write_urdf(tree, origins, out)
    assert out.read_bytes() == text.encode("utf-8")
    again = parse_urdf(out)
    for old, new in zip(tree.joints, again.joints):
        if old.name in origins:
            assert (new.xyz, new.rpy) == origins[old.name]
            assert new.xyz != old.xyz
            old = JointSpec(**{**old.__dict__, "xyz": new.xyz, "rpy": new.rpy})
        assert new == old
    assert (again.links, again.root, again.name) == (tree.links, tree.root, tree.name)
    # Nothing else moved: same lines, visuals/collisions/inertials/comments/transmissions byte-identical.
    assert text.count("\n") == tree.text.count("\n")
    for pattern in (r"<visual>.*?</visual>", r"<collision>.*?</collision>", r"<inertial>.*?</inertial>",
                    r"<!--.*?-->", r"<transmission.*?</transmission>", r"\A<\?xml[^>]*\?>"):
        assert re.findall(pattern, text, re.S) == re.findall(pattern, tree.text, re.S)
    changed = [(a, b) for a, b in zip(tree.text.splitlines(), text.splitlines()) if a != b]
    assert len(changed) == len(names)
    assert all("<origin" in a and "<origin" in b for a, b in changed)
    # Only the origins differ: blank the joint origins of both texts and compare.
    assert _strip_joint_origins(text) == _strip_joint_origins(tree.text)


def test_write_identity_keeps_values(tmp_path):
    tree = parse_urdf(real("meca500"))
    text = write_urdf(tree, {j.name: (j.xyz, j.rpy) for j in tree.joints})
    assert parse_urdf(text).joints == tree.joints


EDGE = """<?xml version="1.0"?>
<!-- header comment -->
<robot name='edge'>
  <link name='base'><visual><origin xyz="5 5 5" rpy="0 0 0"/></visual></link>
  <link name="l1"/> <link name="l2"/> <link name="l3"/> <link name="l4"/>
  <joint type="revolute" name='no_origin'>
    <parent link="base"/>
    <child link="l1"/>
    <axis xyz="0 0 1"/>
  </joint>
  <joint name="closed" type="fixed"/>
  <joint name="inline" type="fixed" ><parent link="l1"/><child link="l2"/></joint>
  <joint name="partial"   type="prismatic">
    <!-- <origin xyz="7 7 7"/> a commented-out origin -->
    <origin rpy = '0.5 0 0' />
    <parent link="l2"/><child link="l3"/><axis xyz="1 0 0"/>
  </joint>
  <joint name="quoted" type="fixed"><origin xyz='1 2 3' rpy="0 0 0"></origin><parent link="l3"/>
    <child link="l4"/></joint>
  <transmission name="t"><joint name="partial"><origin xyz="8 8 8"/></joint></transmission>
</robot>
"""


def test_write_edge_cases():
    # "closed" has no links; make it a valid tree by giving the self-closing joint its own test below.
    text = EDGE.replace('  <joint name="closed" type="fixed"/>\n', "")
    tree = parse_urdf(text)
    origins = {"no_origin": ((0.1, -0.2, 0.3), (1e-17, 0.0, -3.141592653589793)),
               "partial": ((1, 2, 3), (0.25, 0.5, 0.75)),
               "quoted": ((-1.5, 2.5e-9, 1e20), (0, 0, 0)),
               "inline": ((4, 5, 6), (0.1, 0.2, 0.3))}
    out = write_urdf(tree, origins)
    again = parse_urdf(out)
    for name, (xyz, rpy) in origins.items():
        j = again.joint(name)
        assert j.xyz == tuple(float(v) for v in xyz) and j.rpy == tuple(float(v) for v in rpy)
        assert (j.axis, j.parent, j.child, j.type) == (tree.joint(name).axis, tree.joint(name).parent,
                                                        tree.joint(name).child, tree.joint(name).type)
    assert '<origin xyz="0.1 -0.2 0.3" rpy="1e-17 0.0 -3.141592653589793"/>' in out
    assert "<joint type=\"revolute\" name='no_origin'>\n    <origin xyz=" in out  # indented, first child
    assert "<origin rpy = '0.25 0.5 0.75' xyz=\"1.0 2.0 3.0\" />" in out  # quotes kept, xyz appended
    assert "<origin xyz='-1.5 2.5e-09 1e+20' rpy=\"0.0 0.0 0.0\"></origin>" in out
    assert '<joint name="inline" type="fixed" ><origin xyz="4.0 5.0 6.0" rpy="0.1 0.2 0.3"/><parent' in out
    for untouched in ('<origin xyz="5 5 5" rpy="0 0 0"/>', "<!-- header comment -->",
                      '<!-- <origin xyz="7 7 7"/> a commented-out origin -->',
                      '<joint name="partial"><origin xyz="8 8 8"/></joint>'):
        assert untouched in out
    assert out.count("\n") == text.count("\n") + 1  # one inserted origin line


def test_write_inline_joint():
    text = ('<robot name="sc">\n  <link name="a"/>\n  <link name="b"/>\n'
            '  <joint name="j" type="floating"><parent link="a"/><child link="b"/></joint>\n'
            '  <joint name="j2" type="fixed"/>\n</robot>\n')
    # A self-closing top-level joint is invalid URDF (no parent/child), so parse the valid text and write
    # into a hand-made tree whose text has the self-closing form.
    tree = parse_urdf(text.replace('  <joint name="j2" type="fixed"/>\n', ""))
    assert tree.joint("j").type == "floating"
    hand = URDFTree(tree.name, tree.links, tree.joints + (JointSpec("j2", "fixed", "a", "b"),), "a", text)
    out = write_urdf(hand, {"j2": ((1, 2, 3), (0, 0, 0.5))})
    assert '  <joint name="j2" type="fixed"><origin xyz="1.0 2.0 3.0" rpy="0.0 0.0 0.5"/></joint>\n' in out
    inserted = '<origin xyz="1.0 2.0 3.0" rpy="0.0 0.0 0.5"/></joint>'
    assert out.replace(inserted, "") == text.replace("/>\n</robot>", ">\n</robot>")


def test_write_errors(tmp_path):
    tree = parse_urdf(CHAIN)
    with pytest.raises(ModelError, match="'nope'"):
        write_urdf(tree, {"nope": ((0, 0, 0), (0, 0, 0))})
    with pytest.raises(ModelError, match="'j1'"):
        write_urdf(tree, {"j1": ((0, 0), (0, 0, 0))})
    with pytest.raises(ModelError, match="'j1'"):
        write_urdf(tree, {"j1": ((0, float("nan"), 0), (0, 0, 0))})
    assert not list(tmp_path.iterdir())


def test_velocity_limits_are_the_files_limit_velocity():
    """``URDFChain.velocity_limits`` against the file read by ElementTree: fr3.urdf's ``<limit velocity=>``
    in joint order and the chain's dtype; a chain with a joint that has none gives None."""
    import xml.etree.ElementTree as ET

    import torch

    from diffkin import models
    from tests.helpers import FR3

    chain = models.from_urdf(FR3, "fr3_link8", dtype=torch.float32)
    root = ET.parse(FR3).getroot()
    ref = {j.get("name"): float(j.find("limit").get("velocity")) for j in root.iter("joint")
           if j.find("limit") is not None and j.find("limit").get("velocity") is not None}
    v = chain.velocity_limits()
    assert v.dtype == torch.float32 and v.tolist() == pytest.approx([ref[n] for n in chain.joint_names])
    assert len(set(v.tolist())) > 1  # per joint, not one number
    text = FR3.read_text()
    j1 = text.index('name="fr3_joint1"')
    text = text[:j1] + text[j1:].replace('velocity="', 'v_removed="', 1)  # fr3_joint1's velocity gone
    assert models.from_urdf(text, "fr3_link8").velocity_limits() is None
