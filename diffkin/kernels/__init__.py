"""The kernel layer: the only encodings of the kinematic formulas, as pure functions over tensors.

Everything above it (the chains in :mod:`diffkin.chain` and :mod:`diffkin.models`, :mod:`diffkin.jacobian`,
:mod:`diffkin.ik`, :mod:`diffkin.calibration`, the environments) calls these functions; none re-encodes them.

=================  ===========================================================================================
module             encodes
=================  ===========================================================================================
``columns``        a frame as its four columns ``x, y, z, p``: right-multiplication by a fixed transform or
                   by a joint motion about z, in the batch-last (``(3, B)``) or batch-first (``(..., 3)``)
                   layout; writing frames out as ``(..., 4, 4)``
``joints``         each joint kind as fixed transforms around a motion about z: standard DH (2.52), modified
                   DH (Craig), DH with Hayati's β, the general joint (URDF origin xyz + rpy, arbitrary axis);
                   the base / tool pose correction
``tree``           the product along a tree of joints (2.50): every frame, the joint axes and origins, the
                   end links; mimic couplings q_full = M q + b
``jacobian``       the geometric Jacobian (3.30) of every end link from axes and origins, masked by ancestry
                   and summed over mimic followers; the parameter Jacobian (pose w.r.t. geometry)
``dls``            the damped least-squares solve (3.59)
``banded``         the block-banded SPD solve (a Gauss–Newton normal matrix over a time series): block
                   Cholesky, and block-Jacobi conjugate gradients; the scalar tridiagonal solve (splines)
``pose_error``     the pose / orientation error (§3.7.3)
``native``         a second implementation, in C, of the hot path of the above for CPU calls without
                   autograd: the tree product with the Jacobian, and the IK solver's Levenberg–Marquardt
                   iteration (pose error, damped solve); tested for equality against the torch modules
=================  ===========================================================================================

The modules import only :mod:`torch`, :mod:`diffkin._numerics`, :mod:`diffkin.rotations`,
:mod:`diffkin.transforms` and each other (``native`` also the standard library's ``ctypes`` and the C
compiler, once).
"""
