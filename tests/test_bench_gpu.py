"""benchmarks/gpu.py (FK, Jacobian and ik.solve at batch 10⁶ on CUDA) run on the CPU with a tiny batch, so
the script cannot rot; on a CUDA machine the graph and compile rows are checked against the eager call."""

from __future__ import annotations

import pytest
import torch

from benchmarks import gpu


def _rows(*argv):
    return gpu.run(gpu.parse_args(["--quick", *argv]))


def test_gpu_benchmark_runs_on_the_cpu(capsys):
    rows = _rows("--device", "cpu", "--batch", "40", "--ik-batch", "6")
    assert [(r["workload"], r["impl"]) for r in rows] == [("fk", "eager"), ("jacobian", "eager"),
                                                         ("ik.solve", "eager")]
    for r in rows:
        assert r["device"] == "cpu" and r["dtype"] == "float32" and r["seconds"] > 0
        assert r["per_s"] == pytest.approx(r["batch"] / r["seconds"])
    assert rows[0]["batch"] == 40 and rows[2]["batch"] == 6
    assert rows[2]["success"] == 1.0  # reachable targets (FK of random configurations)
    assert gpu.main(["--device", "cpu", "--batch", "8", "--ik-batch", "2", "--quick", "--dtype",
                     "float64"]) == 0
    out = capsys.readouterr().out
    assert "ik.solve" in out and "float64" in out


def test_a_form_that_fails_is_a_row_not_a_crash():
    def fk(q):  # data-dependent Python control flow: fullgraph compile refuses it
        return q * 2 if bool(q.sum() > 0) else q

    q = torch.ones(4, 7)
    rows = gpu._kernel_rows("fk", fk, q, "cpu", (0.0, 1), graphs=True, compiled=True)
    assert rows[0]["impl"] == "eager" and rows[0]["seconds"] > 0
    assert rows[1]["impl"] == "torch.compile" and rows[1]["note"].startswith("failed:")


def test_without_cuda_the_default_device_says_what_to_do():
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    with pytest.raises(SystemExit, match="--device cpu"):
        _rows("--batch", "8")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_graph_and_compile_rows_equal_the_eager_call_on_cuda():
    rows = _rows("--device", "cuda", "--batch", "4096", "--ik-batch", "64")
    by = {(r["workload"], r["impl"]): r for r in rows}
    for name in ("fk", "jacobian"):
        for impl in ("cuda graph", "torch.compile"):
            assert by[(name, impl)]["max_abs_diff_vs_eager"] <= 1e-5, by[(name, impl)]
    assert by[("ik.solve", "eager")]["success"] >= 0.99
