"""The self-collision rows of the whole-clip retargeting (issue 37): their cost, in the same run, against
the clip without them and against their Jacobian by autograd through every body's FK.

The five shipped subject-131 clips batched (B = 5, the first 74 frames each; ``--quick``: 24) on the MJCF
chain of the 29-DoF G1, ``retarget.clip(..., warm_start="batched", velocity_limit=)`` with the URDF's
velocity limits: ``none`` without ``collision``, ``bodies`` with ``collision=retarget.g1_collision(chain)``
(the rows' Jacobian from the bodies' Jacobians, the default), ``autograd`` with the same rows' Jacobian by
autograd (:meth:`SelfCollisionRows.jacobian <diffkin.retarget.self_collision.SelfCollisionRows.jacobian>`
with ``autograd=True``); each at ``--iterations`` whole-clip iterations (default: ``clip``'s, 10 without
and 20 with a collision model). frames/s: the median of three runs (autograd: two), interleaved. Every row
also gives the smallest pair distance over all frames (negative: penetration) and the frames where a pair
penetrates, by the collision model's distances (equal to MuJoCo's ``mj_geomDistance``).
"""

from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import cli


def run(args) -> list[dict]:
    from benchmarks.bench_retarget import CLIPS, g1_velocity_limits
    from diffkin import models, retarget
    from diffkin.retarget.self_collision import SelfCollisionRows

    frames = 24 if args.quick else 74
    mp = retarget.Mapping.builtin("g1")
    mj = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float64).requires_grad_(False)
    clips = [retarget.load_bvh(retarget.example_clips()[n]).frames_slice(0, frames) for n in CLIPS]
    motion = retarget.Motion(torch.cat([c.positions for c in clips]), clips[0].names, clips[0].fps,
                             torch.cat([c.orientations for c in clips]))
    vmax = {j: v for j, v in g1_velocity_limits().items() if j in mj.joint_names}
    rc = retarget.g1_collision(mj)
    bodies = SelfCollisionRows.jacobian

    def autograd(self, q, autograd=False, below=None):
        return bodies(self, q, True)

    def once(kind: str):
        SelfCollisionRows.jacobian = autograd if kind == "autograd" else bodies
        try:
            t0 = time.perf_counter()
            r = retarget.clip(mj, motion, mp, warm_start="batched", velocity_limit=vmax,
                              collision=None if kind == "none" else rc, iterations=args.iterations)
            return time.perf_counter() - t0, r
        finally:
            SelfCollisionRows.jacobian = bodies

    once("bodies")  # warm-up: the C library, the companion chain of the bodies
    times: dict[str, list] = {"none": [], "bodies": [], "autograd": []}
    out = {}
    for rep in range(3):
        for kind in times:
            if kind == "autograd" and rep == 2:  # the slow one: two runs
                continue
            t, out[kind] = once(kind)
            times[kind].append(t)
    n = motion.batch * motion.frames
    rows = []
    for kind, ts in times.items():
        r = out[kind]
        d = rc.self_distances(r.q.reshape(-1, mj.nq)).reshape(*r.q.shape[:2], -1)
        rows.append({"rows' Jacobian": kind, "iterations": r.cost.shape[0] - 1,
                     "frames/s": n / sorted(ts)[len(ts) // 2], "min distance mm": 1000 * float(d.min()),
                     "penetrating frames": int((d.amin(-1) < 0).sum()),
                     "keypoint mm": float(r.metrics.keypoint_error.mean()),
                     "max |dq| vs bodies": float((r.q - out["bodies"].q).abs().max())})
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=None, help="whole-clip iterations (default: clip's)")
    return cli(p, run, "self-collision rows in the whole-clip retargeting (5 clips batched, MJCF G1)", argv)


if __name__ == "__main__":
    raise SystemExit(main())
