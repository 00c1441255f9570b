"""FK of a MuJoCo humanoid, every body: diffkin's MJCF chain against MuJoCo's own ``mj_kinematics`` looped
over the rows and against pytorch-kinematics on the same MJCF, in one run.

The model is Menagerie's Unitree G1 (tests/data/mjcf/unitree_g1/g1.xml: a free joint and 37 hinges, 38
bodies). pytorch-kinematics cannot load a free joint (its MJCF reader maps hinge and slide joints only), so
its rows use the same file with the free joint removed (a fixed pelvis), and diffkin is timed on both.
diffkin's rows are its default CPU path without autograd (the fused C kernel of diffkin.kernels.native, which
runs the free joint's translation and quaternion itself) and the torch kernels it falls back to
(``native.disabled()``), in the same run.

    python -m benchmarks.bench_mjcf [--quick] [--threads N]
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import FULL, QUICK, print_table, timeit, torch_threads
from diffkin.kernels import native

G1 = Path(__file__).resolve().parents[1] / "tests" / "data" / "mjcf" / "unitree_g1" / "g1.xml"


def _specs():
    import mujoco

    from diffkin.models.mjcf import _strip_assets

    floating = mujoco.MjSpec.from_file(str(G1))
    _strip_assets(floating)
    fixed = floating.copy()
    for joint in list(fixed.joints):
        if joint.type == mujoco.mjtJoint.mjJNT_FREE:
            fixed.delete(joint)
    return floating.to_xml(), fixed.to_xml()


def _mujoco_per_row(xml: str, qpos: np.ndarray) -> float:
    """Seconds per row of ``mj_kinematics`` looped over the rows (the call a user's loop makes)."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        for row in qpos:
            d.qpos[:] = row
            mujoco.mj_kinematics(m, d)
        times.append((time.perf_counter() - t0) / len(qpos))
    return float(np.median(times))


def run(args) -> list[dict]:
    import mujoco

    from diffkin.models import from_mjcf

    quick = getattr(args, "quick", False)
    threads = getattr(args, "threads", 1)
    min_time, repeats = QUICK if quick else FULL
    batch = 2_000 if quick else 100_000
    rows: list[dict] = []
    floating_xml, fixed_xml = _specs()
    with torch_threads(threads):
        for label, xml in (("G1 floating base", floating_xml), ("G1 fixed pelvis", fixed_xml)):
            m = mujoco.MjModel.from_xml_string(xml)
            bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, m.nbody)]
            if label == "G1 fixed pelvis":
                bodies = bodies[1:]  # the pelvis is fixed to the world there
            for dtype in (torch.float32, torch.float64):
                chain = from_mjcf(xml, bodies, dtype=dtype)
                chain.requires_grad_(False)
                q = chain.random_configuration(batch, generator=torch.Generator().manual_seed(0))
                ours = _diffkin_rows(chain, q, label, len(bodies), min_time, repeats)
                rows += ours
                if dtype == torch.float64:
                    qpos = chain.to_qpos(q[: min(batch, 5_000)]).numpy()
                    t_mj = _mujoco_per_row(xml, qpos)
                    rows.append({"benchmark": "MJCF FK, every body", "model": label,
                                 "impl": "mujoco mj_kinematics (loop)", "dtype": "float64",
                                 "batch": len(qpos), "bodies": len(bodies), "us_per_row": 1e6 * t_mj})
                    for r in ours:
                        r["ratio_vs_mujoco"] = 1e6 * t_mj / r["us_per_row"]
            if label == "G1 fixed pelvis":
                rows += _pk_rows(xml, batch, min_time, repeats, rows)
    return rows


def _diffkin_rows(chain, q, label: str, bodies: int, min_time: float, repeats: int) -> list[dict]:
    """diffkin's default path (the C kernel where built) and its torch kernels, on the same q."""
    out = []
    paths = (("diffkin C", contextlib.nullcontext), ("diffkin torch", native.disabled))
    for impl, context in paths if native.available() else paths[1:]:
        with torch.no_grad(), context():
            t = timeit(lambda chain=chain, q=q: chain.forward_kinematics(q), min_time, repeats)
        out.append({"benchmark": "MJCF FK, every body", "model": label, "impl": impl,
                    "dtype": str(q.dtype).replace("torch.", ""), "batch": q.shape[0], "bodies": bodies,
                    "us_per_row": 1e6 * t / q.shape[0]})
    return out


def _pk_rows(xml: str, batch: int, min_time: float, repeats: int, rows: list[dict]) -> list[dict]:
    try:
        import pytorch_kinematics as pk
    except ImportError:
        return []
    import pytorch_kinematics.mjcf as pk_mjcf

    # pytorch-kinematics 0.10 keys its joint-type map by mujoco's enum, which mujoco 4 no longer hashes
    # like the int32 ids it reads: add the int keys so its reader runs at all
    int_keys = {int(k): v for k, v in pk_mjcf.JOINT_TYPE_MAP.items()}
    pk_mjcf.JOINT_TYPE_MAP.clear()
    pk_mjcf.JOINT_TYPE_MAP.update(int_keys)
    out = []
    for dtype in (torch.float32, torch.float64):
        chain = pk.build_chain_from_mjcf(xml).to(dtype=dtype)
        q = torch.rand(batch, chain.n_joints, dtype=dtype)
        with torch.no_grad():
            t = timeit(lambda chain=chain, q=q: chain.forward_kinematics(q), min_time, repeats)
        for ours in (r for r in rows if r["model"] == "G1 fixed pelvis" and r["impl"].startswith("diffkin")
                     and r["dtype"] == str(dtype).replace("torch.", "")):
            ours["speedup_vs_pk"] = t / (ours["us_per_row"] * 1e-6 * batch)
        out.append({"benchmark": "MJCF FK, every body", "model": "G1 fixed pelvis",
                    "impl": "pytorch-kinematics", "dtype": str(dtype).replace("torch.", ""), "batch": batch,
                    "bodies": ours["bodies"], "us_per_row": 1e6 * t / batch})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    rows = run(args)
    print_table(rows, rows[0]["benchmark"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
