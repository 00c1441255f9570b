"""``diffkin models``: the built-in robots (DH tables, URDF and MuJoCo files), or one robot's table."""

from __future__ import annotations

import torch

from ..errors import DiffkinError
from ._common import (
    _console,
    _table,
)


# ------------------------------------------------------------------------------------------ models
def cmd_models(args) -> int:
    from .. import models

    con = _console()
    if args.action == "show":
        if not args.name:
            raise DiffkinError("usage: diffkin models show NAME")
        robot = models.info(args.name)
        if robot.format != "dh":  # a URDF / MuJoCo robot: its joints, limits and where it comes from
            chain = models.load(args.name, dtype=torch.float64)
            kinds = getattr(chain, "joint_kinds", None) or ["-"] * len(chain.joint_names)
            rows = [[i + 1, name, kind] for i, (name, kind) in enumerate(zip(chain.joint_names, kinds))]
            con.print(_table(f"{robot.name} ({robot.format.upper()}, nq {chain.nq}, nv {chain.nv}; end links "
                             f"{', '.join(robot.end_links or ())})", ["joint", "name", "kind"], rows))
            con.print(f"file: {robot.path}\nsource: {robot.source}\nlicence: {robot.licence}")
            return 0
        chain = models.load(args.name, dtype=torch.float64)
        rows = []
        for i, (a, al, d, th) in enumerate(chain.dh_table().tolist()):
            lo_hi = "-" if chain.q_limits is None else "[{:.4f}, {:.4f}]".format(*chain.q_limits[i].tolist())
            rows.append(
                [i + 1, chain.joint_types[i], f"{a:.6g}", f"{al:.6g}", f"{d:.6g}", f"{th:.6g}", lo_hi]
            )
        con.print(
            _table(
                f"{chain.name} ({chain.convention} DH)",
                ["joint", "type", "a [m]", "alpha [rad]", "d [m]", "theta [rad]", "limits"],
                rows,
            )
        )
        return 0
    rows, files = [], []
    for robot in models.available(details=True):
        if robot.format == "dh":
            chain = models.load(robot.name, dtype=torch.float64)
            rows.append([robot.name, chain.n_joints, chain.joint_types, chain.convention, robot.source])
        else:  # listed from the catalogue, not compiled: `diffkin models show NAME` loads one
            files.append([robot.name, ", ".join(robot.aliases) or "-", robot.format.upper(), robot.category,
                          ", ".join(robot.end_links or ()), robot.licence])
    con.print(_table("built-in robots (DH tables)", ["name", "DOF", "joints", "DH", "source"], rows))
    con.print(_table("built-in robots (URDF and MuJoCo files; `diffkin models show NAME` for one)",
                     ["name", "aliases", "format", "kind", "default end links", "licence"], files))
    return 0
