"""FK of a MuJoCo humanoid, every body: diffkin's MJCF chain against MuJoCo's own ``mj_kinematics`` looped
over the rows and against pytorch-kinematics on the same MJCF, in one run.

The model is Menagerie's Unitree G1 (tests/data/mjcf/unitree_g1/g1.xml: a free joint and 37 hinges, 38
bodies). pytorch-kinematics cannot load a free joint (its MJCF reader maps hinge and slide joints only), so
its rows use the same file with the free joint removed (a fixed pelvis), and diffkin is timed on both.
diffkin's rows are its default CPU path without autograd (the fused C kernel of diffkin.kernels.native, which
runs the free joint's translation and quaternion itself) and the torch kernels it falls back to
(``native.disabled()``), in the same run.

``--ik``: whole-body IK of the floating-base G1 instead (both feet and both hands, full poses, float64,
0.1 mm / 1 mrad): ``ik.solve`` through the C solve (``dk_solve``, steps on the manifold) against the torch
loop it replaced for ball and free joints (the scheduled loop with the fused FK + Jacobian), one target per
call (median) and a batch (interleaved repeats); success checked by an independent FK.

    python -m benchmarks.bench_mjcf [--quick] [--threads N] [--ik]
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


IK_ENDS = ["left_ankle_roll_link", "right_ankle_roll_link", "left_zero_link", "right_zero_link"]


@contextlib.contextmanager
def _torch_loop():
    """ik.solve as it ran before the C solve took quaternion chains: both C-solve gates closed (the
    scheduled torch loop; its FK and Jacobians still fused)."""
    from diffkin.ik import numerical

    gates = numerical.native_applies, numerical.native_solve_one
    numerical.native_applies, numerical.native_solve_one = (lambda *a: False), (lambda *a, **k: None)
    try:
        yield
    finally:
        numerical.native_applies, numerical.native_solve_one = gates


def _ik_check(chain, res, T) -> dict:
    with torch.no_grad(), native.disabled():
        Te = chain.forward_kinematics(res.q.detach())
    pe = (Te[..., :3, 3] - T[..., :3, 3]).norm(dim=-1).amax(-1)
    R = Te[..., :3, :3].transpose(-1, -2) @ T[..., :3, :3]
    oe = torch.arccos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)).amax(-1)
    ok = (pe <= 1e-4) & (oe <= 1e-3) & chain.within_limits(res.q.detach())
    return {"success": float(ok.double().mean()), "flags_honest": not bool((res.success & ~ok).any())}


def ik_rows(quick: bool, threads: int) -> list[dict]:
    """Whole-body IK of the floating-base G1: the C solve against the torch loop (see the module doc)."""
    from diffkin import ik
    from diffkin.models import from_mjcf

    chain = from_mjcf(G1, IK_ENDS, dtype=torch.float64).requires_grad_(False)
    n_one, N, repeats = (8, 64, 2) if quick else (40, 500, 3)
    # targets from a generator no solve below uses (the torch loop samples its pose library from the
    # solve's generator: targets drawn from the same seed would sit in its library)
    q = chain.random_configuration(max(n_one, N), generator=torch.Generator().manual_seed(2026))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    impls = (("C solve (dk_solve)", contextlib.nullcontext), ("torch loop", _torch_loop))
    rows = []
    with torch_threads(threads), torch.no_grad():
        for impl, context in impls:
            with context():
                ik.solve(chain, T[0], seed=1)  # warm-up: the per-chain state
                times, out = [], []
                for i in range(n_one):
                    t0 = time.perf_counter()
                    out.append(ik.solve(chain, T[i], seed=1 + i))
                    times.append(time.perf_counter() - t0)
            res = ik.IKResult(*(torch.stack([getattr(r, f) for r in out]) for f in
                                ("q", "success", "position_error", "orientation_error", "iterations",
                                 "seeds_tried")))
            s = float(np.median(times))
            rows.append({"case": "1 target per call", "impl": impl, "targets": n_one, "median_ms": 1e3 * s,
                         "solves_per_s": 1 / s, **_ik_check(chain, res, T[:n_one])})
        times = {impl: [] for impl, _ in impls}
        for rep in range(repeats):  # interleaved: both see the same machine load
            for impl, context in impls:
                with context():
                    t0 = time.perf_counter()
                    res = ik.solve(chain, T[:N], seed=1 + rep)
                    times[impl].append(time.perf_counter() - t0)
                check = _ik_check(chain, res, T[:N])
                if rep == repeats - 1:
                    s = float(np.median(times[impl]))
                    rows.append({"case": f"batch of {N}", "impl": impl, "targets": N, "median_ms": 1e3 * s,
                                 "solves_per_s": N / s, **check})
    for case in {r["case"] for r in rows}:
        c, t = (r for r in rows if r["case"] == case)
        c["speedup_vs_torch_loop"] = t["median_ms"] / c["median_ms"]
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--ik", action="store_true", help="whole-body IK of the floating-base G1 instead of FK")
    args = p.parse_args(argv)
    if args.ik:
        print_table(ik_rows(args.quick, args.threads),
                    f"G1 floating base, whole-body ik.solve (4 end links, float64, {args.threads} thread(s))")
        return 0
    rows = run(args)
    print_table(rows, rows[0]["benchmark"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
