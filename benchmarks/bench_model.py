"""The one model on URDF chains and trees: URDF vs DH chain of the same robot, and a tree in one pass.

    python -m benchmarks.bench_model [--batch 100000] [--dtype float32] [--threads 1] [--quick]

* ``urdf_vs_dh``: the Panda as ``models.load("panda")`` (modified DH) and as ``from_urdf(panda.urdf,
  "panda_link8")`` (the same frames), FK and FK + Jacobian, with pytorch-kinematics's serial chain of the
  same URDF timed in the same run. ``ratio_vs_dh`` = DH time / this time (1.0: as fast as the DH chain).
* ``tree``: the allegro hand's four fingertips (``tests/data/urdf/allegro_right_hand.urdf``) as one
  ``from_urdf(..., [4 tips])`` against four separate single-tip diffkin chains and four pytorch-kinematics
  serial chains, FK of all four tips per call.

All under ``torch.no_grad()`` with the same random joints; medians of :func:`benchmarks.common.timeit`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from benchmarks.common import FULL, QUICK, pk_panda, print_table, timeit, torch_threads
from diffkin import models
from diffkin.jacobian import forward_kinematics_and_jacobian

__all__ = ["run", "main"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
ALLEGRO = Path(__file__).resolve().parents[1] / "tests" / "data" / "urdf" / "allegro_right_hand.urdf"
TIPS = [f"link_{i}.0_tip" for i in (3, 7, 11, 15)]


def _urdf_vs_dh(B: int, dtype, min_time: float, repeats: int) -> list[dict]:
    dh = models.load("panda", dtype=dtype)
    urdf = models.from_urdf(models.DATA_DIR / "panda.urdf", "panda_link8", dtype=dtype)
    pk = pk_panda(dtype)
    q = dh.random_configuration((B,), generator=torch.Generator().manual_seed(0))
    rows = []
    with torch.no_grad():
        err = float((urdf.forward_kinematics(q) - dh.forward_kinematics(q)).abs().max())
        for what, fns in (
            ("fk", {"diffkin DH": lambda: dh.forward_kinematics(q),
                    "diffkin URDF": lambda: urdf.forward_kinematics(q),
                    "pytorch_kinematics": lambda: pk.forward_kinematics(q).get_matrix()}),
            ("fk+jacobian", {"diffkin DH": lambda: forward_kinematics_and_jacobian(dh, q),
                             "diffkin URDF": lambda: forward_kinematics_and_jacobian(urdf, q),
                             "pytorch_kinematics": lambda: pk.jacobian(q, ret_eef_pose=True)}),
        ):
            times = {name: timeit(fn, min_time, repeats) for name, fn in fns.items()}
            for name, t in times.items():
                rows.append({"benchmark": "urdf_vs_dh", "what": what, "impl": name, "dtype": str(dtype)[6:],
                             "batch": B, "seconds": t, "configs_per_s": B / t,
                             "ratio_vs_dh": times["diffkin DH"] / t,
                             "speedup_vs_pk": times["pytorch_kinematics"] / t,
                             "max_abs_diff_urdf_dh": err})
    return rows


def _tree(B: int, dtype, min_time: float, repeats: int) -> list[dict]:
    import pytorch_kinematics as pk

    tree = models.from_urdf(ALLEGRO, TIPS, dtype=dtype)
    singles = [models.from_urdf(ALLEGRO, tip, dtype=dtype) for tip in TIPS]
    data = ALLEGRO.read_bytes()
    pks = [pk.build_serial_chain_from_urdf(data, tip).to(dtype=dtype) for tip in TIPS]
    q = tree.random_configuration((B,), generator=torch.Generator().manual_seed(1))
    # each single chain's joints are the tree's joints with the same names
    cols = [[tree.joint_names.index(nm) for nm in c.joint_names] for c in singles]
    qs = [q[:, c].contiguous() for c in cols]
    with torch.no_grad():
        T = tree.forward_kinematics(q)
        err = max(float((T[:, k] - c.forward_kinematics(qk)).abs().max())
                  for k, (c, qk) in enumerate(zip(singles, qs)))
        fns = {"diffkin tree (one pass, K=4)": lambda: tree.forward_kinematics(q),
               "diffkin 4 serial chains": lambda: [c.forward_kinematics(qk) for c, qk in zip(singles, qs)],
               "pytorch_kinematics 4 serial chains": lambda: [c.forward_kinematics(qk).get_matrix()
                                                             for c, qk in zip(pks, qs)]}
        times = {name: timeit(fn, min_time, repeats) for name, fn in fns.items()}
    ref = times["diffkin 4 serial chains"]
    return [{"benchmark": "tree", "impl": name, "dtype": str(dtype)[6:], "batch": B, "seconds": t,
             "configs_per_s": B / t, "ratio_vs_4_serial": ref / t,
             "speedup_vs_pk": times["pytorch_kinematics 4 serial chains"] / t,
             "max_abs_diff_tree_serial": err}
            for name, t in times.items()]


def run(args=None) -> list[dict]:
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    batches = getattr(args, "batch", None) or ([10000] if quick else [1000, 100000])
    dtypes = getattr(args, "dtype", None) or ["float32"]
    threads = getattr(args, "threads", None) or 1
    min_time, repeats = QUICK if quick else FULL
    rows = []
    with torch_threads(threads):
        for name in dtypes:
            for B in batches:
                rows += _urdf_vs_dh(B, _DTYPES[name], min_time, repeats)
                rows += _tree(B, _DTYPES[name], min_time, repeats)
    for r in rows:
        r["threads"] = threads
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, nargs="+", default=None, help="batch sizes (default 1000 100000)")
    p.add_argument("--dtype", nargs="+", choices=sorted(_DTYPES), default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    for title in ("urdf_vs_dh", "tree"):
        print_table([r for r in rows if r["benchmark"] == title], title)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
