"""Second derivatives of the collision distances: gradgradcheck (float64) of every primitive pair at generic
configurations (closest points inside segments and faces, away from kinks), and a distance Hessian
against central differences of its exact gradient."""

import pytest
import torch
from torch.autograd import gradcheck, gradgradcheck

from diffkin.collision import boxes as B
from diffkin.collision import cylinders as C
from diffkin.collision import distances as D

DT = torch.float64
R = torch.tensor(0.1, dtype=DT)
BOX = B.box(torch.zeros(3, dtype=DT), torch.tensor([0.3, 0.4, 0.5], dtype=DT), torch.tensor([0.1, 0.2, 0.3],
                                                                                              dtype=DT))
N = torch.nn.functional.normalize(torch.tensor([0.1, 0.2, 1.0], dtype=DT), dim=0)


def _pairs(a0, a1, b0, b1):
    return D.capsule_capsule_pairs(torch.stack((a0, b0)), torch.stack((a1, b1)), torch.stack((R, R)),
                                   torch.tensor([0]), torch.tensor([1]))


# each: (function, points); the closest points are interior to both segments / to a box face
CASES = {
    "sphere_sphere": (lambda x, y: D.sphere_sphere(x, R, y, R), ([0.1, 1.0, 0.3], [1.0, 0.2, 0.0])),
    "sphere_capsule": (lambda x, p, q: D.sphere_capsule(x, R, p, q, R),
                       ([0.1, 1.0, 0.3], [-1.0, 0.0, 0.0], [1.0, 0.2, 0.0])),
    "capsule_capsule": (lambda w, x, y, z: D.capsule_capsule(w, x, R, y, z, R),
                        ([0.2, -1.0, 1.0], [-0.1, 1.0, 1.2], [-1.0, 0.0, 0.0], [1.0, 0.2, 0.0])),
    "capsule_capsule_pairs": (_pairs,
                              ([0.2, -1.0, 1.0], [-0.1, 1.0, 1.2], [-1.0, 0.0, 0.0], [1.0, 0.2, 0.0])),
    "capsule_box": (lambda x, y, c: B.capsule_box(x, y, R, c, BOX.rotation, BOX.half_extents),
                    ([0.9, -1.0, 0.1], [1.1, 1.0, 0.05], [0.0, 0.0, 0.0])),
    "sphere_box": (lambda x, c: B.sphere_box(x, R, c, BOX.rotation, BOX.half_extents),
                   ([0.9, -1.0, 0.1], [0.0, 0.0, 0.0])),
    "box_box": (lambda c, d: B.box_box(c, BOX.rotation, BOX.half_extents, d, BOX.rotation, BOX.half_extents),
                ([0.0, 0.0, 0.0], [1.0, 0.9, 1.1])),
    "capsule_halfspace": (lambda w, x: D.capsule_halfspace(w, x, R, N, torch.tensor(-1.0, dtype=DT)),
                          ([0.2, -1.0, 1.0], [-0.1, 1.0, 1.2])),
    "sphere_cylinder": (lambda x, p, q: C.sphere_cylinder(x, R, p, q, R),
                        ([0.1, 1.0, 0.3], [-1.0, 0.0, 0.0], [1.0, 0.2, 0.0])),
    "cylinder_halfspace": (lambda w, x: C.cylinder_halfspace(w, x, R, N, torch.tensor(-1.0, dtype=DT)),
                           ([0.2, -1.0, 1.0], [-0.1, 1.0, 1.2])),
    "capsule_cylinder": (lambda w, x, y, z: C.capsule_cylinder(w, x, R, y, z, R),
                         ([0.2, -1.0, 1.0], [-0.1, 1.0, 1.2], [-1.0, 0.0, 0.0], [1.0, 0.2, 0.0])),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_gradgradcheck(name):
    f, pts = CASES[name]
    args = tuple(torch.tensor(p, dtype=DT, requires_grad=True) for p in pts)
    assert gradcheck(f, args) and gradgradcheck(f, args)


def _hessian_vs_fd(f, x, h=1e-5):
    H = torch.autograd.functional.hessian(f, x)
    g = lambda y: torch.autograd.grad(f(y.requires_grad_()), y)[0]  # noqa: E731
    fd = torch.stack([(g(x + h * e) - g(x - h * e)) / (2 * h) for e in torch.eye(len(x), dtype=DT)])
    return H, fd


@pytest.mark.parametrize("name", ["sphere_capsule", "capsule_capsule", "capsule_capsule_pairs",
                                  "capsule_box"])
def test_hessian_matches_differences_of_the_gradient(name):
    """The reported defect: an error of O(1) in a capsule–sphere Hessian, in a neighbourhood (not a kink)."""
    f, pts = CASES[name]
    x0 = torch.tensor(pts, dtype=DT).reshape(-1)
    sizes = [len(p) for p in pts]
    fx = lambda x: f(*x.split(sizes)).sum()  # noqa: E731
    for k in range(3):  # a neighbourhood of the configuration
        x = x0 + 0.01 * k * torch.linspace(-1.0, 1.0, len(x0), dtype=DT)
        H, fd = _hessian_vs_fd(fx, x)
        assert (H - H.T).abs().max() < 1e-10
        assert (H - fd).abs().max() < 1e-6 * (1.0 + fd.abs().max()), (H - fd).abs().max()


def test_batched_hessian_no_nan_at_degenerate_inputs():
    """Coincident and parallel segments and zero-length capsules: finite second derivatives."""
    a0 = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0], [0.3, 0.1, 0]], dtype=DT, requires_grad=True)
    a1 = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0], [0.3, 0.1, 0]], dtype=DT, requires_grad=True)
    b0 = torch.tensor([[0.0, 0, 0], [0.0, 1, 0], [0.0, 0, 0], [0.0, 0, 0]], dtype=DT, requires_grad=True)
    b1 = torch.tensor([[1.0, 0, 0], [1.0, 1, 0], [1.0, 0, 0], [1.0, 0, 0]], dtype=DT, requires_grad=True)
    for d in (D.capsule_capsule(a0, a1, R, b0, b1, R), D.sphere_capsule(a0, R, b0, b1, R),
              B.capsule_box(a0, a1, R, b0, BOX.rotation, BOX.half_extents)):
        g = torch.autograd.grad(d.sum(), (a0, a1, b0, b1), create_graph=True, allow_unused=True)
        s = sum((x * x).sum() for x in g if x is not None)
        for x in torch.autograd.grad(s, (a0, a1, b0, b1), allow_unused=True):
            assert x is None or torch.isfinite(x).all()


def test_pair_kernel_under_functorch_transforms():
    """``torch.func.jacrev`` / ``vmap`` over the robot's self distances (the pair kernel): the same Jacobian
    as autograd's through the closed-form backward (the autograd.Function alone cannot run under them)."""
    from tests.helpers import fr3_robot

    chain, rc = fr3_robot(torch.float64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(0))
    J = torch.func.vmap(torch.func.jacrev(lambda x: rc.self_distances(x[None])[0]))(q)
    want = torch.stack([torch.autograd.functional.jacobian(lambda x: rc.self_distances(x[None])[0], q[k])
                        for k in range(3)])
    assert J.shape == want.shape == (3, rc.self_distances(q).shape[-1], chain.nq)
    torch.testing.assert_close(J, want, rtol=1e-10, atol=1e-12)
