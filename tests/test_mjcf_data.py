"""The vendored MuJoCo Menagerie models (tests/data/mjcf) and the recipe that compiles them without meshes.

Every entry of ``tests/data/mjcf/index.json`` is compiled with ``compile_without_assets`` and checked
against the index (sizes, joint kinds, equality constraints, floating base, named end bodies and sites);
the recipe itself is checked against a second, independent route -- MuJoCo compiling the untouched XML
with stand-in asset files served from memory -- on every body and site frame at random configurations.
"""

import json
from pathlib import Path

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from tests.mjcf_util import compile_with_stand_in_assets, compile_without_assets  # noqa: E402

DATA = Path(__file__).parent / "data" / "mjcf"
INDEX = json.loads((DATA / "index.json").read_text())
# keyed by int: the compiled model's arrays hold plain integers, not the pybind enums
JOINT_KINDS = {
    int(mujoco.mjtJoint.mjJNT_FREE): "free",
    int(mujoco.mjtJoint.mjJNT_BALL): "ball",
    int(mujoco.mjtJoint.mjJNT_SLIDE): "slide",
    int(mujoco.mjtJoint.mjJNT_HINGE): "hinge",
}
EQUALITY_KINDS = {
    int(mujoco.mjtEq.mjEQ_CONNECT): "connect",
    int(mujoco.mjtEq.mjEQ_WELD): "weld",
    int(mujoco.mjtEq.mjEQ_JOINT): "joint",
    int(mujoco.mjtEq.mjEQ_TENDON): "tendon",
}
CATEGORIES = {"arm", "hand", "humanoid", "quadruped", "bimanual", "mobile"}
IDS = [entry["file"] for entry in INDEX]


def test_index_lists_every_vendored_model_once():
    """Every XML under tests/data/mjcf is an index entry or a file one includes; every category is there."""
    listed = [entry["file"] for entry in INDEX]
    included = [name for entry in INDEX for name in entry.get("includes", [])]
    on_disk = sorted(p.relative_to(DATA).as_posix() for p in DATA.rglob("*.xml"))
    assert len(set(listed)) == len(listed) >= 15
    assert sorted(listed + included) == on_disk
    assert {entry["category"] for entry in INDEX} == CATEGORIES


def test_direct_load_needs_the_recipe():
    """Without the recipe MuJoCo refuses a vendored model: the mesh files really are absent."""
    with pytest.raises(ValueError, match="Error opening file"):
        mujoco.MjModel.from_xml_path(str(DATA / "franka_emika_panda" / "panda.xml"))


@pytest.mark.parametrize("entry", INDEX, ids=IDS)
def test_model_compiles_as_indexed(entry):
    """Sizes, joint kinds, equality kinds and the floating base match the index; end bodies/sites exist."""
    model = compile_without_assets(DATA / entry["file"])
    assert (model.nq, model.nv, model.nbody) == (entry["nq"], entry["nv"], entry["nbody"])
    assert {JOINT_KINDS[int(t)] for t in model.jnt_type} == set(entry["joint_types"])
    assert [EQUALITY_KINDS[int(t)] for t in model.eq_type] == entry["equality"]
    # floating: the first joint is a free joint on a child of the world
    free_root = model.njnt > 0 and JOINT_KINDS[int(model.jnt_type[0])] == "free"
    assert (free_root and model.body_parentid[model.jnt_bodyid[0]] == 0) == entry["floating"]
    for name in entry["end_bodies"]:
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name) >= 0, name
    for name in entry["end_sites"]:
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name) >= 0, name
    for name in entry.get("multi_joint_bodies", []):
        assert model.body_jntnum[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)] > 1, name


@pytest.mark.parametrize("entry", INDEX, ids=IDS)
def test_recipe_keeps_kinematics(entry):
    """compile_without_assets and the untouched XML with stand-in assets give the same frames everywhere.

    Random configurations are drawn on the manifold (``mj_integratePos`` from ``qpos0`` with random
    velocities), so ball and free joints get unit quaternions; every body and site pose must agree
    exactly up to round-off.
    """
    stripped = compile_without_assets(DATA / entry["file"])
    reference = compile_with_stand_in_assets(DATA / entry["file"])
    assert (stripped.nq, stripped.nv, stripped.nbody, stripped.nsite) == (
        reference.nq, reference.nv, reference.nbody, reference.nsite)
    np.testing.assert_array_equal(stripped.body_parentid, reference.body_parentid)
    np.testing.assert_array_equal(stripped.qpos0, reference.qpos0)
    data_s, data_r = mujoco.MjData(stripped), mujoco.MjData(reference)
    rng = np.random.default_rng(26)
    for _ in range(3):
        qpos = stripped.qpos0.copy()
        mujoco.mj_integratePos(stripped, qpos, rng.normal(size=stripped.nv), 1.0)
        data_s.qpos[:] = qpos
        data_r.qpos[:] = qpos
        mujoco.mj_kinematics(stripped, data_s)
        mujoco.mj_kinematics(reference, data_r)
        for field in ("xpos", "xmat", "site_xpos", "site_xmat"):
            np.testing.assert_allclose(getattr(data_s, field), getattr(data_r, field), rtol=0, atol=1e-12)
