"""The block-banded SPD solves (diffkin.kernels.banded) against torch's dense solve, and their gradients."""

from __future__ import annotations

import pytest
import torch

from diffkin.kernels.banded import block_banded_cg, block_banded_solve, tridiagonal_solve

F64 = torch.float64


def _system(B: int, T: int, n: int, seed: int):
    """A random SPD block-banded H (two bands) as a product J^T J of random rows coupling frames t-2..t,
    its blocks (D, E, F) and the dense matrix."""
    g = torch.Generator().manual_seed(seed)
    J = torch.zeros(B, T, 2 * n, T * n, dtype=F64)  # frame t's rows touch columns of frames t-2, t-1, t
    for t in range(T):
        for s in range(max(0, t - 2), t + 1):
            J[:, t, :, s * n:(s + 1) * n] = torch.randn(B, 2 * n, n, generator=g, dtype=F64)
    J = J.reshape(B, T * 2 * n, T * n)
    H = J.mT @ J + 1e-3 * torch.eye(T * n, dtype=F64)
    blk = H.reshape(B, T, n, T, n).permute(0, 1, 3, 2, 4)  # (B, T, T, n, n)
    idx = torch.arange(T)
    D = blk[:, idx, idx]
    E = torch.zeros_like(D)
    F = torch.zeros_like(D)
    E[:, 1:] = blk[:, idx[1:], idx[:-1]]
    F[:, 2:] = blk[:, idx[2:], idx[:-2]]
    rhs = torch.randn(B, T, n, generator=g, dtype=F64)
    return H, D, E, F, rhs


@pytest.mark.parametrize("T", [1, 2, 3, 9])
def test_block_banded_solve_against_dense(T):
    H, D, E, F, g = _system(2, T, 4, seed=T)
    want = torch.linalg.solve(H, g.reshape(2, -1)).reshape(g.shape)
    torch.testing.assert_close(block_banded_solve(D, E, F, g), want, atol=1e-9, rtol=1e-9)
    for k in (2, 3, 4):  # regrouped into k-frame super-blocks (block-tridiagonal), padded when k ∤ T
        torch.testing.assert_close(block_banded_solve(D, E, F, g, k), want, atol=1e-9, rtol=1e-9)
    # conjugate gradients: exact in at most T n steps (here with its block-Jacobi preconditioner)
    torch.testing.assert_close(block_banded_cg(D, E, F, g, iterations=4 * T * 4), want, atol=1e-6, rtol=1e-6)


def test_block_banded_solve_gradcheck():
    _, D, E, F, g = _system(1, 4, 2, seed=7)

    def f(D_, g_):
        Ds = 0.5 * (D_ + D_.mT)  # keep the perturbed blocks symmetric
        return block_banded_solve(Ds, E, F, g_)

    assert torch.autograd.gradcheck(f, (D.clone().requires_grad_(), g.clone().requires_grad_()))


def test_tridiagonal_solve_matches_scipy_banded_and_broadcasts():
    """The scalar (non-symmetric) tridiagonal solve against scipy's banded LU, a batched matrix with an
    unbatched right-hand side of the same rank (never read as a batch of vectors), and its gradient."""
    from scipy.linalg import solve_banded

    g = torch.Generator().manual_seed(3)
    B, N, k = 3, 6, 2
    sub, sup = torch.randn(B, N - 1, generator=g, dtype=F64), torch.randn(B, N - 1, generator=g, dtype=F64)
    diag = 4 + torch.rand(B, N, generator=g, dtype=F64)
    rhs = torch.randn(N, k, generator=g, dtype=F64)
    x = tridiagonal_solve(sub, diag, sup, rhs)
    assert x.shape == (B, N, k)
    for b in range(B):
        ab = torch.zeros(3, N, dtype=F64)
        ab[0, 1:], ab[1], ab[2, :-1] = sup[b], diag[b], sub[b]
        torch.testing.assert_close(x[b], torch.from_numpy(solve_banded((1, 1), ab.numpy(), rhs.numpy())))
    args = tuple(a[:1].clone().requires_grad_() for a in (sub, diag, sup)) + (rhs.clone().requires_grad_(),)
    assert torch.autograd.gradcheck(tridiagonal_solve, args)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_banded_solve_against_torch_loop(dtype):
    """The C recursion (native.banded_solve, CPU without autograd) against the torch loop and the dense
    solve, both dtypes, batched (2, 3) with broadcast blocks; a block that is not positive definite gives
    NaN in its system only."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    H, D, E, F, g = _system(6, 7, 5, seed=3)
    D, E, F, g, H = (t.reshape(2, 3, *t.shape[1:]) for t in (D, E, F, g, H))
    D, E, F, g = (t.to(dtype) for t in (D, E, F, g))
    got = native.banded_solve(D, E, F, g)
    assert got is not None and got.dtype == dtype and got.shape == g.shape
    with native.disabled():
        ref = block_banded_solve(D, E, F, g)
    want = torch.linalg.solve(H, g.double().reshape(2, 3, -1, 1)).reshape(g.shape)
    tol = 1e-10 if dtype == torch.float64 else 2e-3
    torch.testing.assert_close(got.double(), want, atol=tol, rtol=tol)
    torch.testing.assert_close(got, ref, atol=tol, rtol=tol)
    torch.testing.assert_close(block_banded_solve(D, E, F, g), got)  # the default path is the C one
    one = native.banded_solve(D[0, 0], E[0, 0], F[0, 0], g[0, 0])  # no batch dimension
    torch.testing.assert_close(one, got[0, 0])
    bad = D.clone()
    bad[1, 2, 4] = -bad[1, 2, 4]  # frame 4 of system (1, 2): negative definite
    x = native.banded_solve(bad, E, F, g)
    assert torch.isnan(x[1, 2]).any() and torch.isfinite(x[0]).all() and torch.isfinite(x[1, :2]).all()
    assert native.banded_solve(D, E, F, g.requires_grad_()) is None  # autograd: the torch loop's


@pytest.mark.parametrize("shape", ["diagonal", "lower"])
def test_native_banded_solve_with_a_triangular_second_band(shape):
    """A second band F_t that is diagonal (the acceleration term of the whole-clip retargeting) or lower
    triangular takes the C recursion's triangular path: the dense solve's answer, block sizes with and
    without a remainder of the 4-row passes (n = 5, 8), against a full F's path on the same system."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    for n in (5, 8):
        _, D, E, F, g = _system(2, 7, n, seed=5)
        F = torch.diag_embed(F.diagonal(dim1=-2, dim2=-1)) if shape == "diagonal" else F.tril()
        D = D + 4 * n * torch.eye(n, dtype=F64)  # diagonally dominant: SPD with any such F
        T = D.shape[1]
        H = torch.zeros(2, T, T, n, n, dtype=F64)
        idx = torch.arange(T)
        H[:, idx, idx] = D
        H[:, idx[1:], idx[:-1]], H[:, idx[:-1], idx[1:]] = E[:, 1:], E[:, 1:].mT
        H[:, idx[2:], idx[:-2]], H[:, idx[:-2], idx[2:]] = F[:, 2:], F[:, 2:].mT
        H = H.permute(0, 1, 3, 2, 4).reshape(2, T * n, T * n)
        want = torch.linalg.solve(H, g.reshape(2, -1, 1)).reshape(g.shape)
        got = native.banded_solve(D, E, F, g)
        torch.testing.assert_close(got, want, atol=1e-10, rtol=1e-10)
        F_full = F.clone()
        F_full[:, 2:, 0, -1] = 1e-30  # one entry above the diagonal: the general path
        torch.testing.assert_close(native.banded_solve(D, E, F_full, g), got, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_banded_solve_shift_is_a_raised_diagonal(dtype):
    """``shift`` (one value per system: the whole-clip LM damping) solves (H + shift I) x = g on the C path
    and on the torch loop (autograd), batched (2, 3), against the dense solve of H + shift I."""
    from diffkin.kernels import native

    H, D, E, F, g = _system(6, 5, 4, seed=11)
    D, E, F, g, H = (t.reshape(2, 3, *t.shape[1:]) for t in (D, E, F, g, H))
    shift = torch.tensor([[0.0, 0.5, 3.0], [10.0, 1e-3, 2.0]], dtype=F64)
    Hs = H + shift[..., None, None] * torch.eye(H.shape[-1], dtype=F64)
    want = torch.linalg.solve(Hs, g.reshape(2, 3, -1, 1)).reshape(g.shape)
    D, E, F, g, s = (t.to(dtype) for t in (D, E, F, g, shift))
    tol = 1e-10 if dtype == torch.float64 else 2e-3
    if native.available():
        got = native.banded_solve(D, E, F, g, s)
        torch.testing.assert_close(got.double(), want, atol=tol, rtol=tol)
        torch.testing.assert_close(block_banded_solve(D, E, F, g, shift=s), got)  # the default path: C's
    x = block_banded_solve(D, E, F, g.clone().requires_grad_(), shift=s)  # autograd: the torch loop
    torch.testing.assert_close(x.detach().double(), want, atol=tol, rtol=tol)
    assert not torch.allclose(x.detach().double(), block_banded_solve(D, E, F, g).double(), atol=tol)


def test_native_banded_solve_with_one_second_band_for_every_system():
    """An F without batch dims (the whole-clip retargeting's acceleration band, the same for every clip) is
    read once for all systems: the dense solve's answer, and the same numbers as F copied per system."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    H, D, E, F, _ = _system(1, 6, 5, seed=5)
    g = torch.randn(3, 6, 5, generator=torch.Generator().manual_seed(1), dtype=F64)
    D3, E3 = D.expand(3, -1, -1, -1), E.expand(3, -1, -1, -1)
    got = native.banded_solve(D3, E3, F[0], g)
    want = torch.linalg.solve(H, g.reshape(3, -1, 1)).reshape(g.shape)
    torch.testing.assert_close(got, want, atol=1e-10, rtol=1e-10)
    assert torch.equal(got, native.banded_solve(D3, E3, F.expand(3, -1, -1, -1), g))
    # a band broadcast along T too (one block for every step) still broadcasts, as F.expand did before
    F1 = F[0, :1]
    want1 = native.banded_solve(D3, E3, F1.expand(3, 6, -1, -1).contiguous(), g)
    assert torch.equal(native.banded_solve(D3, E3, F1, g), want1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_banded_solve_register_tiles_any_block_size(dtype, monkeypatch):
    """The C solve's register tiles (rows padded to whole vectors: 8 doubles, 16 floats; tiles of 4 rows
    and at most 5 vectors) at block sizes with a remainder of rows and of columns, one and several column
    panels (n = 13, 35: the whole-clip retargeting's, 45), a shared F diagonal (its fast path, tested once
    per call), lower triangular and full, against the dense solve; one thread and two the same numbers."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    monkeypatch.setattr(native, "free_cores", lambda: 2)  # two threads whatever the machine's load
    gen = torch.Generator().manual_seed(2)
    for n in (13, 35, 45):
        T = 6
        _, D, E, F, g = _system(3, T, n, seed=n)
        D = D + 4 * n * torch.eye(n, dtype=F64)  # diagonally dominant: SPD with any of the F below
        Ff = 0.3 * torch.randn(T, n, n, generator=gen, dtype=F64)
        for F1 in (torch.diag_embed(Ff.diagonal(dim1=-2, dim2=-1)), Ff.tril(), Ff):
            idx = torch.arange(T)
            H = torch.zeros(3, T, T, n, n, dtype=F64)
            H[:, idx, idx] = D
            H[:, idx[1:], idx[:-1]], H[:, idx[:-1], idx[1:]] = E[:, 1:], E[:, 1:].mT
            H[:, idx[2:], idx[:-2]], H[:, idx[:-2], idx[2:]] = F1[2:], F1[2:].mT
            H = H.permute(0, 1, 3, 2, 4).reshape(3, T * n, T * n)
            want = torch.linalg.solve(H, g.reshape(3, -1, 1)).reshape(g.shape)
            args = tuple(t.to(dtype) for t in (D, E, F1, g))
            got = native.banded_solve(*args)
            tol = 1e-10 if dtype == torch.float64 else 2e-3
            torch.testing.assert_close(got.double(), want, atol=tol, rtol=tol)
            per_system = native.banded_solve(*args[:2], args[2].expand(3, -1, -1, -1), args[3])
            assert torch.equal(per_system, got)  # F tested per system: the same path
            with native.threads(2):
                assert torch.equal(native.banded_solve(*args), got)


def test_tridiagonal_solve_along_the_band_equals_the_dense_solve():
    """tridiagonal_solve(..., dominant=True) above DENSE_MAX rows (the Thomas algorithm: a clamped spline's
    long, refined paths) gives the dense LU's x (1e-12) on diagonally dominant systems with batch dims
    broadcast, and its gradients pass gradcheck."""
    from diffkin.kernels.banded import DENSE_MAX, _thomas, tridiagonal_solve

    g = torch.Generator().manual_seed(0)
    N = DENSE_MAX + 37
    h = torch.rand(3, 1, N - 1, generator=g, dtype=torch.float64) + 0.01
    hl, hr = h[..., :-1], h[..., 1:]
    one, zero = torch.ones_like(h[..., :1]), torch.zeros_like(h[..., :1])
    diag = torch.cat([one, 2 * (hl + hr), one], -1)
    sub, sup = torch.cat([hr, zero], -1), torch.cat([zero, hl], -1)
    rhs = torch.randn(2, N, 4, generator=g, dtype=torch.float64)  # broadcast against (3, 1)
    band = tridiagonal_solve(sub, diag, sup, rhs, dominant=True)
    dense = tridiagonal_solve(sub, diag, sup, rhs)
    assert band.shape == dense.shape == (3, 2, N, 4)
    torch.testing.assert_close(band, dense, rtol=0, atol=1e-12)
    A = torch.diag_embed(diag) + torch.diag_embed(sub, offset=-1) + torch.diag_embed(sup, offset=1)
    torch.testing.assert_close(A @ band, rhs.expand(3, 2, N, 4), rtol=0, atol=1e-12)
    small = [t[0, 0, :6].clone().requires_grad_(True) for t in (sub, diag, sup)]
    small[1] = diag[0, 0, :7].clone().requires_grad_(True)
    b = rhs[0, :7, :2].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(_thomas, (*small, b))


def test_native_banded_solve_in_the_threads_kept_work_space():
    """The C solve and the clip rows run in the calling thread's kept work space (no fresh pages at every
    call): a larger solve, a smaller one, an IK solve that takes the same space with its own layout, then
    the first again give the same floats as the first (nothing a call reads is left from another)."""
    from diffkin import ik, models
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the native kernel is not built")
    big = _system(3, 9, 6, seed=4)[1:]
    small = _system(1, 3, 2, seed=5)[1:]
    first = native.banded_solve(*big)
    want_small = torch.linalg.solve(_system(1, 3, 2, seed=5)[0], small[3].reshape(1, -1, 1)).reshape(1, 3, 2)
    torch.testing.assert_close(native.banded_solve(*small), want_small, atol=1e-10, rtol=1e-10)
    chain = models.load("panda", dtype=F64)
    gen = torch.Generator().manual_seed(0)
    target = chain.forward_kinematics(chain.random_configuration(2, generator=gen))
    assert bool(ik.solve(chain, target, num_seeds=1).success.all())
    assert torch.equal(native.banded_solve(*big), first)
