"""Chunked FK / IK (:mod:`diffkin.io.streaming`): equal to the one-shot results, bounded memory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.errors import DiffkinError
from diffkin.io.data import RandomJoints
from diffkin.io.streaming import _ErrorStats, stream_fk, stream_ik

REPO = Path(__file__).resolve().parent.parent


def fk(chain, q) -> torch.Tensor:
    with torch.no_grad():
        return chain.forward_kinematics(torch.as_tensor(q))


@pytest.fixture(scope="module")
def panda():
    return models.load("panda", dtype=torch.float64)


@pytest.mark.parametrize("chunk", [1, 7, 16, 17, 1000])
def test_streamed_fk_equals_one_shot(tmp_path, panda, chunk):
    q = panda.random_configuration(53, generator=torch.Generator().manual_seed(0))  # 53: no chunk divides it
    np.save(tmp_path / "q.npy", q.numpy())
    res = stream_fk(panda, tmp_path / "q.npy", tmp_path / "T.npy", chunk_size=chunk)
    assert res.count == 53 and res.output == tmp_path / "T.npy"
    T = np.load(tmp_path / "T.npy")
    np.testing.assert_allclose(T, fk(panda, q).numpy(), rtol=0, atol=1e-13)
    assert not list(tmp_path.glob("*.part*"))


def test_random_samples_do_not_depend_on_the_chunk_size(tmp_path, panda):
    stream_fk(panda, RandomJoints(41, seed=3), tmp_path / "a.npz", chunk_size=5)
    stream_fk(panda, RandomJoints(41, seed=3), tmp_path / "b.npz", chunk_size=41)
    stream_fk(panda, RandomJoints(41, seed=4), tmp_path / "c.npz", chunk_size=41)
    with np.load(tmp_path / "a.npz") as a, np.load(tmp_path / "b.npz") as b, np.load(tmp_path / "c.npz") as c:
        np.testing.assert_array_equal(a["q"], b["q"])
        np.testing.assert_allclose(a["T"], b["T"], atol=1e-13)
        assert not np.allclose(a["q"], c["q"])
        lo, hi = (t.numpy() for t in panda.lower_upper())
        assert (a["q"] >= lo).all() and (a["q"] <= hi).all()
        np.testing.assert_allclose(a["T"], fk(panda, a["q"]).numpy(), atol=1e-13)


def test_a_row_slice_equals_the_same_rows_of_the_whole(tmp_path, panda):
    stream_fk(panda, RandomJoints(30, seed=1), tmp_path / "all.csv", chunk_size=8)
    stream_fk(panda, RandomJoints(30, seed=1), tmp_path / "part.csv", chunk_size=4, start=11, stop=23)
    whole = np.loadtxt(tmp_path / "all.csv", delimiter=",", skiprows=1)
    part = np.loadtxt(tmp_path / "part.csv", delimiter=",", skiprows=1)
    assert part.shape == (12, 14)
    np.testing.assert_allclose(part, whole[11:23], atol=1e-13)
    with pytest.raises(DiffkinError, match="start <= stop"):
        stream_fk(panda, RandomJoints(30), None, start=20, stop=40)
    with pytest.raises(DiffkinError, match="chunk_size"):
        stream_fk(panda, RandomJoints(30), None, chunk_size=0)


def test_streamed_fk_from_csv_and_npz_inputs(tmp_path, panda):
    q = panda.random_configuration(23, generator=torch.Generator().manual_seed(2)).numpy()
    np.savez_compressed(tmp_path / "q.npz", q=q)
    np.savetxt(tmp_path / "q.csv", q, delimiter=",", fmt="%.17g")
    ref = fk(panda, q).numpy()
    for name in ("q.npz", "q.csv"):
        stream_fk(panda, tmp_path / name, tmp_path / "T.npy", chunk_size=6)
        np.testing.assert_allclose(np.load(tmp_path / "T.npy"), ref, atol=1e-13)


def test_streamed_ik_success_flags_are_honest(tmp_path, panda):
    res = stream_ik(panda, RandomJoints(20, seed=5), tmp_path / "ik.npz", chunk_size=7, num_seeds=2,
                    max_iterations=6)
    with np.load(tmp_path / "ik.npz") as d:
        q, success, pe, oe = d["q"], d["success"], d["position_error"], d["orientation_error"]
    assert res.count == 20 and res.successes == int(success.sum())
    assert res.failures == 20 - res.successes
    # targets recomputed independently: the FK of the same random configurations
    src = RandomJoints(20, seed=5).source(panda)
    target = fk(panda, np.concatenate(list(src.chunks(20))))
    T = fk(panda, q)
    pos_err = (T[:, :3, 3] - target[:, :3, 3]).norm(dim=-1).numpy()
    cos = ((T[:, :3, :3] * target[:, :3, :3]).sum((-1, -2)) - 1) / 2
    ori_err = torch.arccos(cos.clamp(-1, 1)).numpy()
    np.testing.assert_allclose(pe, pos_err, atol=1e-12)
    np.testing.assert_allclose(oe, ori_err, atol=1e-6)
    within = panda.within_limits(torch.as_tensor(q)).numpy()
    np.testing.assert_array_equal(success, (pos_err <= 1e-4) & (ori_err <= 1e-3) & within)
    assert res.position_error == (pytest.approx(np.median(pe), rel=1e-6), pytest.approx(pe.max()))
    assert res.orientation_error[1] == pytest.approx(oe.max())
    assert 0 < res.successes < 20  # 2 seeds x 6 iterations: some fail, so both kinds of flag are tested


def test_streamed_ik_position_only_and_slices(tmp_path, panda):
    xyz = np.array([[0.4, 0.1, 0.5], [0.3, -0.2, 0.6], [5.0, 0.0, 0.0], [0.5, 0.0, 0.3]])
    np.save(tmp_path / "xyz.npy", xyz)
    res = stream_ik(panda, tmp_path / "xyz.npy", tmp_path / "q.npy", chunk_size=3, start=1, stop=4)
    assert res.position_only and res.orientation_error is None and res.count == 3 and res.failures == 1
    q = np.load(tmp_path / "q.npy")
    assert q.shape == (3, 7)
    p = fk(panda, q)[:, :3, 3].numpy()
    err = np.linalg.norm(p - xyz[1:], axis=-1)
    assert err[0] <= 1e-4 and err[2] <= 1e-4 and err[1] > 3.5
    assert res.position_error[1] == pytest.approx(err[1])
    with pytest.raises(DiffkinError, match="positions only"):
        stream_ik(panda, tmp_path / "xyz.npy", position_only=False)


def test_error_stats_histogram_median():
    rng = np.random.default_rng(0)
    x = 10 ** rng.uniform(-9, -2, 5001)
    exact, hist = _ErrorStats(), _ErrorStats(exact_limit=1000)
    for part in np.array_split(x, 7):
        exact.add(part)
        hist.add(part)
    assert not exact.approximate and hist.approximate
    assert exact.median() == pytest.approx(np.median(x), rel=1e-6)  # float32 storage
    assert hist.median() == pytest.approx(np.median(x), rel=2e-3)
    assert hist.max() == exact.max() == x.max()
    zeros = _ErrorStats(exact_limit=2)
    zeros.add(np.array([0.0, 0.0, 0.0, 1.0]))
    assert zeros.median() == 0.0


def test_fk_memory_does_not_grow_with_n(tmp_path):
    """Peak RSS of a 10x larger FK run grows by far less than its 10x larger output (streamed, not held)."""
    code = ("import resource, sys, torch; from diffkin import models;"
            "from diffkin.io.data import RandomJoints;"
            "from diffkin.io.streaming import stream_fk; torch.set_num_threads(1);"
            "c = models.load('panda', dtype=torch.float64);"
            "stream_fk(c, RandomJoints(int(sys.argv[1])), sys.argv[2], chunk_size=4096);"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    peaks = []
    for n in (30_000, 300_000):
        out = subprocess.run([sys.executable, "-c", code, str(n), str(tmp_path / f"T{n}.npy")], cwd=REPO,
                             capture_output=True, text=True, check=True).stdout
        peaks.append(int(out.split()[-1]) * 1024)
    grown = (300_000 - 30_000) * 128  # bytes of output added
    assert (tmp_path / "T300000.npy").stat().st_size == 300_000 * 128 + 128
    assert peaks[1] - peaks[0] < 0.25 * grown, (peaks, grown)


def test_a_bfloat16_tensor_source_is_widened_like_a_files_numbers(tmp_path, panda):
    # numpy has no bfloat16: the source is converted to float64 first (it was a raw TypeError)
    q16 = panda.random_configuration(9, generator=torch.Generator().manual_seed(1)).to(torch.bfloat16)
    res = stream_fk(panda, q16, tmp_path / "T.npy")
    assert res.count == 9
    expected = fk(panda, q16.double()).numpy()
    np.testing.assert_allclose(np.load(tmp_path / "T.npy"), expected, rtol=0, atol=1e-13)
