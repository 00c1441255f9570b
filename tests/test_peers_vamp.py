"""The parsing and table helpers of the VAMP / OMPL comparison (benchmarks/peers_vamp.py,
benchmarks/bench_motion_problems.py --compare). VAMP itself runs in its own venv and is not needed here."""

import json

import pytest

from benchmarks import bench_motion_problems as bench
from benchmarks import peers_vamp


def _answer(name="box/0001", solved=True, path=None, **extra):
    a = {"name": name, "valid": True, "solved": solved, "plan_ns": 35000, "simplify_ns": 12000,
         "wall_ns": 60000, "iterations": 40, "initial_cost": 5.0, "cost": 4.0,
         "path": [[0.0] * 7, [0.5] * 7] if path is None else path}
    a.update(extra)
    return json.dumps(a)


def test_parse_lines_reads_answers_and_skips_prints():
    text = "\n".join(["Setting planner - range: 1.0", _answer("box/0001"), "",
                      _answer("cage/0002", solved=False, path=[]), "  " + _answer("table_pick/0041")])
    out = peers_vamp.parse_lines(text)
    assert list(out) == ["box/0001", "cage/0002", "table_pick/0041"]
    assert out["box/0001"]["plan_ns"] == 35000 and out["box/0001"]["path"][1] == [0.5] * 7
    assert out["cage/0002"]["solved"] is False and out["cage/0002"]["path"] == []


@pytest.mark.parametrize("line, match", [
    (json.dumps({"name": "box/0001", "solved": True}), "lacks"),
    (_answer(path=[[0.0] * 7]), "path"),
    (_answer(path=[[0.0] * 7, [0.0] * 6]), "path"),
    (_answer(path="[[0, 0]]"), "path"),
])
def test_parse_lines_refuses_malformed_answers(line, match):
    with pytest.raises(ValueError, match=match):
        peers_vamp.parse_lines(line)


def test_format_table_blanks_missing_cells_and_groups_families():
    rows = [{"method": "a", "family": "box", "problems": 2, "success": 1, "ms": 1.23456},
            {"method": "bb", "family": "box", "problems": 2, "duration_s": None},
            {"method": "a", "family": "cage", "problems": 3, "success": 0, "ms": 12345.6}]
    lines = bench.format_table(rows).splitlines()
    head = lines[0].split()
    assert head == ["method", "family", "problems", "success", "ms"]  # all-empty columns dropped
    assert lines[2].split() == ["a", "box", "2", "1", "1.235"]
    assert lines[3].split() == ["bb", "box", "2"]
    assert lines[4] == "" and lines[5].split() == ["a", "cage", "3", "0", "1.235e+04"]
    assert len({len(line) for line in lines if line}) == 1  # fixed width
