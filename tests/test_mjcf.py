"""MJCF chains (diffkin.models.from_mjcf) against MuJoCo itself: every body and site of every vendored
Menagerie model (tests/data/mjcf/index.json) and of a model with every joint type
(tests/data/mjcf_extra/joint_kinds.xml), FK against ``mj_kinematics`` and Jacobians against ``mj_jacBody`` /
``mj_jacSite``, configuration-space operations against ``mj_integratePos`` / ``mj_differentiatePos``, IK
successes re-checked by MuJoCo."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from diffkin import ik  # noqa: E402
from diffkin.errors import ModelError  # noqa: E402
from diffkin.models import from_mjcf as _from_mjcf  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402
from tests.helpers import chain_of_everything, mujoco_frames  # noqa: E402

DATA = Path(__file__).parent / "data"
KINDS = DATA / "mjcf_extra" / "joint_kinds.xml"
ENTRIES = json.loads((DATA / "mjcf" / "index.json").read_text())
MODELS = [DATA / "mjcf" / e["file"] for e in ENTRIES] + [KINDS]


def from_mjcf(source, end_link, **kwargs):
    """The loader in float64 unless told otherwise (the references are MuJoCo's float64 numbers)."""
    kwargs.setdefault("dtype", torch.float64)
    return _from_mjcf(source, end_link, **kwargs)


def _random_qpos(m, rng) -> np.ndarray:
    """A random qpos: hinge/slide within their range (else ±3), unit quaternions for ball and free joints."""
    qpos = m.qpos0.copy()
    for j in range(m.njnt):
        a, t = m.jnt_qposadr[j], m.jnt_type[j]
        if t == mujoco.mjtJoint.mjJNT_FREE:
            qpos[a:a + 3] = rng.normal(size=3)
            qq = rng.normal(size=4)
            qpos[a + 3:a + 7] = qq / np.linalg.norm(qq)
        elif t == mujoco.mjtJoint.mjJNT_BALL:
            qq = rng.normal(size=4)
            qpos[a:a + 4] = qq / np.linalg.norm(qq)
        else:
            lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-3.0, 3.0)
            qpos[a] = rng.uniform(lo, hi)
    return qpos


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.parent.name + "/" + p.name)
def test_every_body_and_site_matches_mujoco(path):
    m, chain, ends, bodies = chain_of_everything(path)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(7)
    qpos = np.stack([_random_qpos(m, rng) for _ in range(24)])
    q = chain.from_qpos(torch.tensor(qpos))
    qpos = chain.to_qpos(q).numpy()  # joints coupled by an equality follow their leader, as in the chain
    ref_T, ref_J = [], []
    for row in qpos:
        d.qpos[:] = row
        T, J = mujoco_frames(m, d, ends, bodies)
        ref_T.append(T)
        ref_J.append(J @ chain.velocity_map().numpy())
    ref_T, ref_J = torch.tensor(np.stack(ref_T)), torch.tensor(np.stack(ref_J))
    with torch.no_grad():  # the batch-last column path (24 rows) and the batch-first matrix path (2 rows)
        T, J = chain.forward_kinematics_and_jacobian(q)
        T2, J2 = chain.forward_kinematics_and_jacobian(q[:2])
    torch.testing.assert_close(T, ref_T, atol=1e-10, rtol=0)
    torch.testing.assert_close(J, ref_J, atol=1e-10, rtol=0)
    torch.testing.assert_close(T2, ref_T[:2], atol=1e-10, rtol=0)
    torch.testing.assert_close(J2, ref_J[:2], atol=1e-10, rtol=0)
    Tg, Jg = chain.forward_kinematics_and_jacobian(q[:20].clone().requires_grad_(True))  # the autograd path
    torch.testing.assert_close(Tg.detach(), ref_T[:20], atol=1e-10, rtol=0)
    torch.testing.assert_close(Jg.detach(), ref_J[:20], atol=1e-10, rtol=0)


def test_float32_and_batch_shapes():
    m, chain64, ends, bodies = chain_of_everything(KINDS)
    chain32 = from_mjcf(KINDS, ends, dtype=torch.float32)
    q = chain64.random_configuration((2, 3), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        T64 = chain64.forward_kinematics(q)
        T32 = chain32.forward_kinematics(q.float())
        assert chain64.forward_kinematics(q[0, 0]).shape == (len(ends), 4, 4)
    assert T64.shape == (2, 3, len(ends), 4, 4) and T32.dtype == torch.float32
    torch.testing.assert_close(T32.double(), T64, atol=2e-6, rtol=0)
    single = from_mjcf(KINDS, "palm", dtype=torch.float64)
    assert single.forward_kinematics(q[..., :single.nq]).shape == (2, 3, 4, 4)


def test_structure_of_the_joint_kinds_model():
    chain = from_mjcf(KINDS, ["hand", "foot", "box"])
    assert chain.joint_names == ["root", "shoulder_ball", "elbow_flex", "elbow_twist", "wrist_slide",
                                 "finger_a", "hip_ball", "knee", "box_x", "box_yaw"]
    assert chain.joint_kinds[:4] == ["free", "ball", "revolute", "revolute"]
    assert (chain.nq, chain.nv) == (22, 19)  # finger_b follows finger_a (an equality): not a variable
    q0 = chain.neutral_configuration()
    assert q0[3:7].tolist() == [1.0, 0.0, 0.0, 0.0] and q0[7:11].tolist() == [1.0, 0.0, 0.0, 0.0]
    m = compile_mjcf(KINDS)[0]
    np.testing.assert_array_equal(chain.to_qpos(chain.from_qpos(torch.tensor(m.qpos0))).numpy()[:-1],
                                  m.qpos0[:-1])


def test_integrate_and_difference_match_mujoco():
    menagerie = DATA / "mjcf"
    for path in (KINDS, menagerie / "unitree_g1" / "g1.xml", menagerie / "agility_cassie" / "cassie.xml"):
        m, chain, _, _ = chain_of_everything(path)
        rng = np.random.default_rng(3)
        for _ in range(10):
            q = chain.from_qpos(torch.tensor(_random_qpos(m, rng)))
            qpos = chain.to_qpos(q).numpy()
            v = torch.tensor(rng.normal(size=chain.nv))
            ref = qpos.copy()
            mujoco.mj_integratePos(m, ref, chain.to_qvel(v).numpy(), 1.0)
            got = chain.to_qpos(chain.integrate(q, v)).numpy()
            np.testing.assert_allclose(got, ref, atol=1e-12)
            q1 = chain.from_qpos(torch.tensor(_random_qpos(m, rng)))
            qvel = np.zeros(m.nv)
            mujoco.mj_differentiatePos(m, qvel, 1.0, qpos, chain.to_qpos(q1).numpy())
            np.testing.assert_allclose(chain.difference(q, q1).numpy(), qvel[chain.dof_index()], atol=1e-12)


def test_sources_text_bytes_and_includes():
    text = KINDS.read_text()
    a = from_mjcf(KINDS, "palm")
    b = from_mjcf(text, "palm")
    c = from_mjcf(text.encode(), "palm")
    q = a.random_configuration(4, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(b.forward_kinematics(q), a.forward_kinematics(q))
        torch.testing.assert_close(c.forward_kinematics(q), a.forward_kinematics(q))
    aloha = from_mjcf(DATA / "mjcf" / "aloha" / "aloha.xml", ["left/gripper_base", "right/gripper_base"])
    assert aloha.n_ends == 2  # aloha.xml includes its actuators from a file next to it


def test_structural_errors_are_typed_and_name_the_element():
    with pytest.raises(ModelError, match="'nope' is neither a body nor a site"):
        from_mjcf(KINDS, "nope")
    with pytest.raises(ModelError, match="root_link 'ghost' is not a body"):
        from_mjcf(KINDS, "palm", root_link="ghost")
    with pytest.raises(ModelError, match="does not hang below root_link 'hip'"):
        from_mjcf(KINDS, "palm", root_link="hip")
    with pytest.raises(ModelError, match="MJCF file not found"):
        from_mjcf("/no/such/model.xml", "x")
    with pytest.raises(ModelError, match="MJCF text.*could not compile"):
        from_mjcf("<mujoco><worldbody><body name='a'><joint type='hinge' axis='0 0 0'/>"
                  "</body></worldbody></mujoco>", "a")
    with pytest.raises(ModelError, match="duplicate"):
        from_mjcf(KINDS, ["palm", "palm"])
    with pytest.raises(ModelError, match="no joint"):
        from_mjcf("<mujoco><worldbody><body name='a'><geom size='0.1'/></body></worldbody></mujoco>", "a")


def test_closed_loops_are_named_in_a_warning():
    with pytest.warns(UserWarning, match="not enforced.*connect"):
        from_mjcf(DATA / "mjcf" / "agility_cassie" / "cassie.xml", "left-foot")


def test_root_link_subtree():
    full = from_mjcf(KINDS, ["elbow", "palm"])
    sub = from_mjcf(KINDS, "palm", root_link="elbow")  # from the elbow body's frame (its joints above it)
    assert sub.joint_names == ["wrist_slide", "finger_a"]
    q = full.random_configuration(3, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        T = full.forward_kinematics(q)
        T_sub = sub.forward_kinematics(q[:, -2:])
    torch.testing.assert_close(T[:, 0] @ T_sub, T[:, 1], atol=1e-12, rtol=0)


def test_floating_base_ik_rechecked_by_mujoco():
    path = DATA / "mjcf" / "unitree_h1" / "h1.xml"
    m = compile_mjcf(path)[0]
    ends = ["left_ankle_link", "right_ankle_link", "left_elbow_link", "right_elbow_link"]
    chain = from_mjcf(path, ends)
    q_true = chain.random_configuration(8, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        T = chain.forward_kinematics(q_true)
    res = ik.solve(chain, T, seed=0, num_seeds=256, max_iterations=48)  # 24 pose rows, 25 DOF
    assert bool(res.success.all())
    d = mujoco.MjData(m)
    for row, Tt in zip(chain.to_qpos(res.q.detach()).numpy(), T.numpy()):
        d.qpos[:] = row
        got, _ = mujoco_frames(m, d, ends, set(ends))
        assert np.abs(got[:, :3, 3] - Tt[:, :3, 3]).max() <= 1e-4
        cos = (np.trace(np.swapaxes(got[:, :3, :3], 1, 2) @ Tt[:, :3, :3], axis1=1, axis2=2) - 1) / 2
        assert np.arccos(np.clip(cos, -1, 1)).max() <= 1e-3
    norms = res.q.detach()[..., 3:7].norm(dim=-1)
    torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-12, rtol=0)


def test_geometry_is_learnable():
    chain = from_mjcf(KINDS, ["palm", "foot"], learnable=True)
    names = {k for k, _ in chain.named_parameters()}
    assert {"body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos", "site_quat"} <= names
    q = chain.random_configuration(5, generator=torch.Generator().manual_seed(5))
    chain.forward_kinematics(q).sum().backward()
    for name in ("body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos"):
        g = getattr(chain, name).grad
        assert g is not None and bool(torch.isfinite(g).all()) and bool(g.abs().sum() > 0), name


def test_geometry_fit_through_fk():
    """Fitting an MJCF chain's body offsets by gradient descent through FK recovers a 2 mm perturbation."""
    path = DATA / "mjcf" / "universal_robots_ur5e" / "ur5e.xml"
    true = from_mjcf(path, "wrist_3_link").requires_grad_(False)
    g = torch.Generator().manual_seed(12)
    with torch.no_grad():
        true.body_pos.add_(0.002 * torch.randn(true.body_pos.shape, generator=g, dtype=torch.float64))
    fit = from_mjcf(path, "wrist_3_link").requires_grad_(False)
    fit.body_pos.requires_grad_(True)
    q, q_test = fit.random_configuration(40, generator=g), fit.random_configuration(200, generator=g)
    with torch.no_grad():
        p, p_test = true.forward_kinematics(q)[..., :3, 3], true.forward_kinematics(q_test)[..., :3, 3]
    opt = torch.optim.LBFGS([fit.body_pos], max_iter=200, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = (fit.forward_kinematics(q)[..., :3, 3] - p).square().sum()
        loss.backward()
        return loss

    with torch.no_grad():
        before = float((fit.forward_kinematics(q_test)[..., :3, 3] - p_test).norm(dim=-1).max())
    opt.step(closure)
    with torch.no_grad():
        after = float((fit.forward_kinematics(q_test)[..., :3, 3] - p_test).norm(dim=-1).max())
    assert before > 1e-3 and after < 1e-5  # 13.6 mm -> 2.6 µm held out (position-only data)


@pytest.mark.parametrize("path, ends", [
    (KINDS, ["hand", "palm", "foot", "tip", "box"]),
    (DATA / "mjcf" / "franka_emika_panda" / "panda.xml", ["hand", "left_finger"]),
    (DATA / "mjcf" / "agility_cassie" / "cassie.xml", ["left-foot", "right-foot"]),
], ids=["joint_kinds", "panda", "cassie"])
def test_to_mjcf_round_trip(path, ends, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chain = from_mjcf(path, ends)
        assert chain.to_mjcf() == chain.source_text  # nothing changed: the file byte for byte
        g = torch.Generator().manual_seed(13)
        with torch.no_grad():
            for name in ("body_pos", "body_quat", "joint_pos", "joint_axis", "site_pos", "site_quat"):
                p = getattr(chain, name)
                p.add_(0.01 * torch.randn(p.shape, generator=g, dtype=p.dtype))
        out = tmp_path / Path(path).name
        text = chain.to_mjcf(out)
        assert out.read_text() == text
        # the lines that changed are those of the elements with parameters; the rest stays as it was
        before, after = chain.source_text.splitlines(), text.splitlines()
        assert len(before) == len(after)
        changed = [a for a, b in zip(before, after) if a != b]
        assert changed and all(re.search(r"<(body|joint|site)\b", line) for line in changed)
        again = from_mjcf(out, ends)
    q = chain.random_configuration(16, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(again.forward_kinematics(q), chain.forward_kinematics(q), atol=1e-10,
                                   rtol=0)
    chain.base = torch.eye(4, dtype=torch.float64)
    with pytest.raises(ModelError, match="base or tool"):
        chain.to_mjcf()


def test_to_dtype_moves_the_reference_qpos_with_the_chain():
    # qpos0 was a plain attribute: after .to(float32) to_qpos mixed float64 and float32 (a raw RuntimeError)
    chain = from_mjcf(KINDS, "palm", root_link="torso", dtype=torch.float64).to(torch.float32)
    q = chain.neutral_configuration()
    assert chain.qpos0.dtype == torch.float32
    torch.testing.assert_close(chain.from_qpos(chain.to_qpos(q)), q)
