"""The kernel layer: the only encodings of the library's shared numerical formulas (package-internal).

Each module here holds the one implementation of a formula that several public functions need, for every
tensor layout they use (batch first ``(..., k)`` for the public API, batch last ``(k, m)`` for the IK inner
loop); public modules are thin wrappers that check their inputs and call these kernels. No input checks here.

- :mod:`.dls`: the damped least-squares solve Δ = Jᵀ(JJᵀ + λI)⁻¹e (3.59) and its matrix form.
- :mod:`.pose_error`: the pose error [p_d − p_e; e_O] with the orientation errors of §3.7.3.
"""
