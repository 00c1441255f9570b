"""Sharded FK / IK (diffkin.io.distributed): shards on chunk boundaries, manifests, merging, and 2-process
gloo runs under torchrun that equal the single-process result row for row."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.cli import main
from diffkin.io import distributed as dist
from diffkin.io.data import DataFileError, open_joint_source, read_array
from diffkin.io.streaming import combine_ik, stream_ik

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("n", "chunk", "world"),
                         [(10, 3, 2), (1000, 64, 3), (5, 8, 4), (7, 1, 7), (64, 64, 2)])
def test_shards_tile_the_rows_on_chunk_boundaries(n, chunk, world):
    rows = [dist.shard_rows(n, chunk, r, world) for r in range(world)]
    assert rows[0][0] == 0 and rows[-1][1] == n
    for (a, b), (c, _) in zip(rows, rows[1:]):
        assert b == c and a <= b
    for a, b in rows:
        assert a % chunk == 0 and (b == n or b % chunk == 0)
    sizes = [-(-(b - a) // chunk) for a, b in rows]  # chunks per rank differ by at most one
    assert max(sizes) - min(sizes) <= 1


def _write_parts(tmp_path, arrays, suffix=".npy"):
    out = tmp_path / f"T{suffix}"
    world = len(arrays)
    rows, a = [], 0
    for r, arr in enumerate(arrays):
        np.save(dist.part_path(out, r, world), arr)
        rows.append((a, a + len(arr)))
        a += len(arr)
    return out, rows


def test_manifest_reads_as_one_data_set_in_any_chunking(tmp_path):
    q = np.random.default_rng(0).uniform(-1, 1, (103, 7))
    out, rows = _write_parts(tmp_path, [q[:40], q[40:90], q[90:]])
    manifest = dist.write_manifest(out, 3, rows, "test")
    assert manifest.name == "T.shards.json"
    assert np.array_equal(read_array(manifest), q)
    src = open_joint_source(manifest, 7)
    for size in (1, 7, 40, 64, 500):
        chunks = list(src.chunks(size, 5, 101))
        assert all(len(c) == size for c in chunks[:-1])  # sizes kept across part boundaries
        assert np.array_equal(np.concatenate(chunks), q[5:101])


def test_manifest_errors_name_the_problem(tmp_path):
    q = np.zeros((10, 7))
    out, rows = _write_parts(tmp_path, [q[:4], q[4:]])
    manifest = dist.write_manifest(out, 2, rows, "test")
    data = json.loads(manifest.read_text())
    data["parts"][1]["rows"] = [5, 10]
    manifest.write_text(json.dumps(data))
    with pytest.raises(DataFileError, match="starts at row 5, expected 4"):
        read_array(manifest)
    dist.write_manifest(out, 2, rows, "test")
    dist.part_path(out, 1, 2).unlink()
    with pytest.raises(DataFileError, match="is missing"):
        read_array(manifest)
    (tmp_path / "x.shards.json").write_text("{}")
    with pytest.raises(DataFileError, match="not a diffkin shard manifest"):
        read_array(tmp_path / "x.shards.json")


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".csv"])
def test_merge_equals_the_concatenation(tmp_path, suffix):
    rng = np.random.default_rng(1)
    parts_data = [rng.normal(size=(m, 3)) for m in (5, 1, 9)]
    flags = [rng.integers(0, 2, m).astype(bool) for m in (5, 1, 9)]
    out = tmp_path / f"x{suffix}"
    parts = [dist.part_path(out, r, 3) for r in range(3)]
    for p, a, f in zip(parts, parts_data, flags):
        if suffix == ".npy":
            np.save(p, a)
        elif suffix == ".npz":
            np.savez(p, a=a, ok=f)
        else:
            np.savetxt(p, a, delimiter=",", header="x,y,z", comments="", fmt="%.17g")
    dist.merge_parts(out, parts, step=2)
    assert not any(p.exists() for p in parts)
    whole = np.concatenate(parts_data)
    if suffix == ".npy":
        assert np.array_equal(np.load(out), whole)
    elif suffix == ".npz":
        with np.load(out) as z:
            assert np.array_equal(z["a"], whole) and np.array_equal(z["ok"], np.concatenate(flags))
            assert z["ok"].dtype == bool
    else:
        assert out.read_text().count("x,y,z") == 1
        assert np.array_equal(np.loadtxt(out, delimiter=",", skiprows=1), whole)


def test_merge_keeps_constant_entries_once_and_agree_in_one_process(tmp_path):
    """``constants`` (entries that are no rows, written whole by the Writer) come once from the first part;
    the other entries concatenate. ``agree`` in one process: ``[value]``, or this process's failure."""
    from diffkin.io.data import open_writer

    rng = np.random.default_rng(2)
    out = tmp_path / "p.npz"
    names = np.array(["j1", "j2", "j3"])
    chunks = [rng.normal(size=(m, 4, 3)) for m in (2, 5)]
    parts = [dist.part_path(out, r, 2) for r in range(2)]
    for p, x in zip(parts, chunks):
        w = open_writer(p, len(x), {"q": ((4, 3), np.float64, []), "why": ((), "<U8", [])},
                        constants={"joint_names": names})
        w.write({"q": x, "why": np.array(["a"] * len(x))})
        w.close()
        with np.load(p) as z:
            assert np.array_equal(z["joint_names"], names) and z["q"].shape == x.shape
    dist.merge_parts(out, parts, step=3, constants=("joint_names",))
    with np.load(out) as z:
        assert sorted(z.files) == ["joint_names", "q", "why"]
        assert np.array_equal(z["q"], np.concatenate(chunks)) and np.array_equal(z["joint_names"], names)
        assert z["why"].tolist() == ["a"] * 7
    assert dist.agree(5) == [5]
    with pytest.raises(ValueError, match="boom"):
        dist.agree(5, ValueError("boom"))


def test_combined_ik_summary_equals_one_run():
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration(300, generator=torch.Generator().manual_seed(3))
    T = chain.forward_kinematics(q).detach().numpy()
    T[::50, 0, 3] += 5.0  # unreachable: failures must add up
    whole = stream_ik(chain, T, chunk_size=64, num_seeds=2)
    parts = [stream_ik(chain, T, chunk_size=64, start=a, stop=b, num_seeds=2)
             for a, b in ((0, 128), (128, 300))]
    got = combine_ik(parts)
    assert (got.count, got.successes) == (whole.count, whole.successes) and got.failures >= 6
    assert got.position_error == whole.position_error
    assert got.orientation_error == whole.orientation_error


def _torchrun(tmp_path, *args):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "diffkin.cli", *args]
    out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


@pytest.mark.slow
def test_two_process_fk_and_ik_equal_one_process(tmp_path):
    """torchrun, 2 processes on gloo: the sharded FK (manifest) and IK (merged .npz) equal main() in one."""
    fk = ["fk", "--robot", "panda", "--random", "3000", "--seed", "4", "--chunk-size", "512"]
    _torchrun(tmp_path, *fk, "--output", "T.npy")
    parts, rows = dist.read_manifest(tmp_path / "T.shards.json")
    assert len(parts) == 2 and rows == 3000
    assert main([*fk, "--output", str(tmp_path / "T1.npy"), "--no-progress"]) == 0
    sharded, single = read_array(tmp_path / "T.shards.json"), np.load(tmp_path / "T1.npy")
    assert sharded.shape == (3000, 4, 4) and np.array_equal(sharded, single)

    ik = ["ik", "--robot", "panda", "--chunk-size", "64", "--num-seeds", "2"]
    out = _torchrun(tmp_path, *ik, "--input", "T.shards.json", "--output", "q.npz", "--merge")
    assert "targets" in out.stdout and "successes" in out.stdout  # one summary, from rank 0
    assert out.stdout.count("successes") == 1
    assert main([*ik, "--input", str(tmp_path / "T1.npy"), "--output", str(tmp_path / "q1.npz"),
                 "--no-progress"]) == 0
    assert not list(tmp_path.glob("q.part-*"))
    with np.load(tmp_path / "q.npz") as a, np.load(tmp_path / "q1.npz") as b:
        assert a["q"].shape == (3000, 7)
        for k in b.files:
            assert np.array_equal(a[k], b[k], equal_nan=True), k


@pytest.mark.slow
def test_a_failing_rank_stops_every_rank_with_one_error_and_no_parts(tmp_path):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration(1200, generator=torch.Generator().manual_seed(5))
    T = chain.forward_kinematics(q).detach().numpy()
    T[1000, 0, 3] = np.nan  # in rank 1's shard
    np.save(tmp_path / "T.npy", T)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m",
           "diffkin.cli", "ik", "--robot", "panda", "--input", "T.npy", "--chunk-size", "300", "--output",
           "q.npy", "--num-seeds", "2"]
    out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert out.returncode != 0
    errors = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert any("row 1001" in ln for ln in errors), out.stderr[-3000:]
    assert all("internal error" not in ln for ln in errors), errors
    assert sorted(p.name for p in tmp_path.iterdir()) == ["T.npy"]  # no parts, no manifest


# ------------------------------------------------------------------- the Python API (issue 30 item 17)
def _api_rank(rank: int, world: int, port: int, out: str, merge: bool) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    from diffkin.io.data import RandomJoints
    from diffkin.io.streaming import stream_fk

    torch.set_num_threads(1)
    chain = models.load("panda", dtype=torch.float64)
    res = dist.run_sharded(stream_fk, chain, RandomJoints(300, 2), out, chunk_size=64, merge=merge)
    assert (res is None) == (rank != 0)
    if rank == 0:
        assert res.count == 300 and Path(res.output).exists()


# two more processes (12 s); test_two_process_fk_and_ik_equal_one_process keeps sharding in the default run
@pytest.mark.extended
def test_run_sharded_python_api_equals_one_process(tmp_path):
    """``distributed.run_sharded`` (what ``diffkin fk|ik`` calls under torchrun) in 2 gloo processes: the
    manifest (and the merged file) equal one process's output; in one process it is ``stream`` itself."""
    import socket

    import torch.multiprocessing as mp

    from diffkin.io.data import RandomJoints
    from diffkin.io.streaming import stream_fk

    chain = models.load("panda", dtype=torch.float64)
    one = dist.run_sharded(stream_fk, chain, RandomJoints(300, 2), tmp_path / "one.npy", chunk_size=64)
    assert one.count == 300 and one.output == tmp_path / "one.npy"
    for merge, name in ((False, "T.npy"), (True, "M.npz")):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        mp.spawn(_api_rank, args=(2, port, str(tmp_path / name), merge), nprocs=2, join=True)
    assert np.array_equal(read_array(tmp_path / "T.shards.json"), np.load(tmp_path / "one.npy"))
    with np.load(tmp_path / "M.npz") as z:
        assert np.array_equal(z["T"], np.load(tmp_path / "one.npy"))
    assert not list(tmp_path.glob("M.part-*"))


def test_cli_holds_no_sharding_orchestration():
    """Gather, clean-up, manifest and merge live in diffkin.io.distributed (the CLI calls run_sharded)."""
    import inspect

    import diffkin.cli as cli

    text = inspect.getsource(cli)
    for name in ("gather(", "part_path(", "write_manifest(", "merge_parts(", "shard_rows("):
        assert name not in text, name
