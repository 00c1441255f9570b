"""``diffkin fk --random`` / ``diffkin ik`` with ``--self-collision`` / ``--world FILE`` / ``--margin``: the
samples re-checked by coal with the geoms placed by Pinocchio (never by the code under test); the world
file reader; the option errors."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import ik
from diffkin.cli import main
from diffkin.collision import World, box, read_world
from diffkin.errors import ModelError, ShapeError

pin = pytest.importorskip("pinocchio")
import collision_reference as ref  # noqa: E402
from test_collision_robot import FR3, _Pinocchio, _robot  # noqa: E402

from tests.helpers import FR3_SRDF_NEVER  # noqa: E402

EXAMPLE = Path(__file__).parent.parent / "examples" / "world.yaml"
F64 = torch.float64


def _run(capsys, *args) -> tuple[int, str]:
    rc = main([str(a) for a in args])
    out = capsys.readouterr()
    return rc, out.out + out.err


def _coal_min(q: np.ndarray, pairs: bool = True) -> np.ndarray:
    """The smallest distance of each row by coal: the SRDF-filtered self pairs (if ``pairs``) and every geom
    against the example world."""
    chain, rc = _robot(FR3, "fr3_link8")
    rc_pairs = {p for p in _robot_with_srdf().pairs}
    pref = _Pinocchio(FR3.read_text(), chain, rc.geoms)
    objs = ref.world_objects(read_world(EXAMPLE, dtype=F64))
    out = []
    for row in q:
        pref.place(row)
        d = [ref.distance(*pref.shape(a), *pref.shape(b)) for a, b in rc_pairs] if pairs else []
        d += [ref.distance(*pref.shape(g.name), *o) for g in rc.geoms for o in objs]
        out.append(min(d))
    return np.array(out)


def _robot_with_srdf():
    import warnings

    from diffkin import models
    from diffkin.collision import RobotCollision

    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobotCollision.from_urdf(FR3, chain, srdf=FR3_SRDF_NEVER)


def test_fk_random_collision_free_rechecked_by_coal(capsys, tmp_path):
    srdf = tmp_path / "fr3.srdf"
    srdf.write_text(FR3_SRDF_NEVER)
    out = tmp_path / "fk.npz"
    rc, text = _run(capsys, "fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 60, "--seed", 3,
                    "--self-collision", "--srdf", srdf, "--world", EXAMPLE, "--margin", 0.01, "--output", out,
                    "--chunk-size", 25)
    assert rc == 0, text
    with np.load(out) as d:
        q, T = d["q"], d["T"]
    assert q.shape == (60, 7) and T.shape == (60, 4, 4)
    assert _coal_min(q).min() >= 0.01 - 1e-8
    assert len(np.unique(q.round(12), axis=0)) == 60
    # the same seed, the same samples; plain --random of the same robot does collide
    rc, _ = _run(capsys, "fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 60, "--seed", 3,
                 "--self-collision", "--srdf", srdf, "--world", EXAMPLE, "--margin", 0.01, "--output",
                 tmp_path / "again.npz", "--chunk-size", 25)
    with np.load(tmp_path / "again.npz") as d:
        np.testing.assert_array_equal(d["q"], q)
    rc, _ = _run(capsys, "fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 60, "--output",
                 tmp_path / "plain.npz")
    with np.load(tmp_path / "plain.npz") as d:
        assert (_coal_min(d["q"]) < 0.01).mean() > 0.3
    # --world alone: the self pairs do not count (link1/link3 always overlap: no SRDF needed)
    rc, text = _run(capsys, "fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 30, "--world",
                    EXAMPLE, "--output", tmp_path / "world.npz")
    assert rc == 0, text
    with np.load(tmp_path / "world.npz") as d:
        assert _coal_min(d["q"], pairs=False).min() >= -1e-8


def test_ik_collision_options(capsys, tmp_path):
    """With ik.solve(collision=, world=, margin=) (the collision-aware IK branch) the successes are
    re-checked by coal; without it the options are one clear error."""
    srdf = tmp_path / "fr3.srdf"
    srdf.write_text(FR3_SRDF_NEVER)
    args = ("ik", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 12, "--self-collision", "--srdf",
            srdf, "--world", EXAMPLE, "--margin", 0.005, "--output", tmp_path / "ik.npz")
    rc, text = _run(capsys, *args)
    if "collision" not in inspect.signature(ik.solve).parameters:
        assert rc == 2 and "no collision= keyword" in text
        return
    assert rc == 0, text
    with np.load(tmp_path / "ik.npz") as d:
        q, ok = d["q"], d["success"].astype(bool)
    assert ok.mean() > 0.5
    assert _coal_min(q[ok]).min() >= 0.005 - 1e-6


def test_option_errors(capsys, tmp_path):
    cases = [
        (("fk", "--robot", "panda", "--random", 3, "--self-collision"), "--urdf FILE or --mjcf FILE"),
        (("fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 3, "--margin", 0.1), "--margin"),
        (("fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 3, "--world", EXAMPLE, "--margin", -1),
         "--margin"),
        (("fk", "--urdf", FR3, "--end-link", "fr3_link8", "--input", tmp_path / "q.npy", "--world", EXAMPLE),
         "apply to --random"),
        (("fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 3, "--world", tmp_path / "none.yaml"),
         "not found"),
        (("fk", "--mjcf", "tests/data/mjcf/franka_emika_panda/panda.xml", "--random", 3), "--end-link"),
    ]
    np.save(tmp_path / "q.npy", np.zeros((2, 7)))
    for args, message in cases:
        rc, text = _run(capsys, *args)
        assert rc == 2 and message in text, (args, text)


def test_world_files(tmp_path):
    w = read_world(EXAMPLE, dtype=F64)
    assert w.counts == (2, 1, 1, 1, 1, 0) and w.dtype == F64
    direct = World(spheres=[[0.45, 0.0, 0.45, 0.12], [0.0, 0.4, 0.3, 0.08]],
                   capsules=[[0.3, -0.4, 0.2, 0.3, -0.4, 0.7, 0.04]],
                   boxes=box([[-0.4, 0.0, 0.3]], [[0.05, 0.2, 0.3]], [[0.0, 0.0, 0.3]], dtype=F64),
                   halfspaces=[[0.0, 0.0, 1.0, -0.15]], points=[[0.3, 0.1, 0.9]], dtype=F64)
    for a, b in ((w.spheres, direct.spheres), (w.capsules, direct.capsules),
                 (w.halfspaces, direct.halfspaces), (w.points, direct.points),
                 (w.boxes.rotation, direct.boxes.rotation)):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    js = tmp_path / "w.json"
    js.write_text('{"spheres": [[0, 0, 1, 0.2]], '
                  '"boxes": [{"center": [1, 0, 0], "half_extents": [0.1, 0.1, 0.1]}]}')
    wj = read_world(js, dtype=torch.float32)
    assert wj.counts == (1, 0, 1, 0, 0, 0) and wj.dtype == torch.float32
    assert len(read_world(_write(tmp_path, "empty.yaml", ""))) == 0
    bad = {  # the file's layout and the World's values: typed errors naming the file, expected and got
        "cones: [[1, 2]]": (ModelError, r"unknown key\(s\) cones; expected keys among spheres, capsules"),
        "spheres: [[1, 2]]": (ShapeError, r"bad1.yaml: expected spheres of shape .*, got \(1, 2\)"),
        "- 1": (ModelError, "expected a mapping with keys spheres, .*, got list"),
        "boxes: [{center: [0, 0, 0]}]":
            (ModelError, r"boxes\[0\]: expected keys center, half_extents .*got center"),
        "boxes: [{center: [0, 0, 0], half_extents: [1, -1, 1]}]":
            (ModelError, r"boxes: expected half_extents >= 0, got 1 negative value\(s\) \(smallest -1\)"),
        "halfspaces: [[0, 0, 2, 0]]": (ModelError, r"expected unit half-space normals, got norms \[2.0\]"),
        "cylinders: [[0, 0, 1, 0, 0, 1, 0.1]]":
            (ModelError, r"bad6.yaml: expected cylinders lengths \|b - a\|"),
        "spheres: [": (ModelError, "expected YAML / JSON, cannot read the world file"),
    }
    for i, (text, (cls, message)) in enumerate(bad.items()):
        with pytest.raises(cls, match=message):
            read_world(_write(tmp_path, f"bad{i}.yaml", text))
    with pytest.raises(ModelError, match=r"world file '.*nowhere.yaml' not found \(expected an existing"):
        read_world(tmp_path / "nowhere.yaml")


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_fk_of_an_mjcf_robot_against_mujoco(capsys, tmp_path):
    """``--mjcf FILE --end-link BODY`` (the one loader): the poses written are MuJoCo's."""
    mujoco = pytest.importorskip("mujoco")
    from mjcf_util import compile_with_stand_in_assets

    path = Path(__file__).parent / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
    rc, text = _run(capsys, "fk", "--mjcf", path, "--end-link", "hand", "--random", 8, "--output",
                    tmp_path / "fk.npz")
    assert rc == 0, text
    with np.load(tmp_path / "fk.npz") as d:
        q, T = d["q"], d["T"]
    m = compile_with_stand_in_assets(path)
    data = mujoco.MjData(m)
    hand = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "hand")
    for row, pose in zip(q, T):
        data.qpos[:7] = row
        mujoco.mj_kinematics(m, data)
        np.testing.assert_allclose(pose[:3, 3], data.xpos[hand], atol=1e-12)
        np.testing.assert_allclose(pose[:3, :3], data.xmat[hand].reshape(3, 3), atol=1e-12)


def test_the_docs_command_lines_run_as_written(capsys, tmp_path, monkeypatch):
    """docs/collision.md's two command lines, from the repository root as written (fewer samples, outputs
    under tmp): every sample and every solution flagged a success is collision-free by coal."""
    root = Path(__file__).parent.parent
    block = (root / "docs" / "collision.md").read_text().split("## On the command line")[1].split("```")[1]
    commands = [line.split() for line in block.replace("\\\n", " ").strip().splitlines()]
    assert [c[:2] for c in commands] == [["diffkin", "fk"], ["diffkin", "ik"]]
    monkeypatch.chdir(root)
    for argv in commands:
        argv = argv[1:]
        argv[argv.index("--random") + 1] = "12"
        k = argv.index("--output") + 1
        argv[k] = str(tmp_path / argv[k])
        rc, text = _run(capsys, *argv)
        assert rc == 0, text
        with np.load(argv[k]) as d:
            q = d["q"] if argv[0] == "fk" else d["q"][d["success"]]
        assert len(q) >= (12 if argv[0] == "fk" else 9)
        margin = float(argv[argv.index("--margin") + 1]) if "--margin" in argv else 0.0
        assert _coal_min(q).min() >= margin - 1e-7


def test_no_srdf_fails_fast_naming_the_pair(capsys):
    """Without the SRDF no FR3 sample is free of self-collision: the error comes after the first rounds and
    names the link-1 × link-3 pair (issue 27 review: it ran 5 min 17 s before)."""
    rc, text = _run(capsys, "fk", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 200,
                    "--self-collision")
    assert rc != 0
    assert "stopped early" in text and re.search(r"fr3_link1_sc/\d × fr3_link3_sc/\d \(100 %\)", text), text


def test_ik_with_a_world_and_no_self_collision(capsys, tmp_path):
    """``--world`` without ``--self-collision`` (the robot against the world only) reaches ik.solve as a
    RobotCollision without self pairs (it was refused there as the CLI's own wrapper type); the successes are
    re-checked against the world by coal."""
    rc, text = _run(capsys, "ik", "--urdf", FR3, "--end-link", "fr3_link8", "--random", 8, "--world", EXAMPLE,
                    "--margin", 0.005, "--output", tmp_path / "ik.npz")
    assert rc == 0, text
    with np.load(tmp_path / "ik.npz") as d:
        q, ok = d["q"], d["success"].astype(bool)
    assert ok.any()
    assert _coal_min(q[ok], pairs=False).min() >= 0.005 - 1e-6


def test_world_only_keeps_the_world_distances_and_drops_the_pairs():
    robot = _robot_with_srdf()
    only = robot.world_only()
    world = read_world(EXAMPLE, dtype=F64)
    q = robot.chain.random_configuration((5,), generator=torch.Generator().manual_seed(3))
    assert only.pairs == [] and only.self_distances(q).shape == (5, 0)
    torch.testing.assert_close(only.world_distances(q, world), robot.world_distances(q, world))
    nearest = robot.world_distances(q, world).flatten(-2).amin(-1)
    torch.testing.assert_close(only.min_distance(q, world), nearest)
