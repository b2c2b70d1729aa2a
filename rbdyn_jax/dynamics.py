"""Right-hand sides of Euler's dynamic equations, absolute and relative.

See the physics guide, docs/physics.md#absolute-motion and docs/physics.md#relative-motion.

Pure functions on arrays: no diffrax, no state classes. Every vector is in **body
components**; `J` is the full (possibly non-diagonal) inertia tensor about the fixed point
or the centre of mass. All functions accept leading `*batch` axes (broadcast between
arguments) and are safe under `jit`, `vmap` and `grad`.
"""

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from ._checks import check_trailing
from ._custom_types import Matrix, MatrixLike, Vector, VectorLike
from ._vector import cross_parts, matvec_parts, split
from .inertia import planar

# The arithmetic below works on a vector's three components as separate arrays and stacks
# them once, where a function returns. XLA:CPU fuses a stack (a concatenation) with all
# that is computed upstream of it and recomputes that, unvectorised, for every component it
# writes; a stack between two operations (a vector sum, say) is one that XLA cannot cancel
# against the slices that follow. It matters for the sensitivities' field, whose vectors
# carry a column axis (the integrator's sensitivities, `integrate/_sensitivity.py`), not for
# the model's own.


def _prepare(J, vectors: dict[str, VectorLike]) -> tuple[Matrix, list[Vector]]:
    """Validate shapes and broadcast the batch axes of `J` (…, 3, 3) and the vectors."""
    J = check_trailing(J, (3, 3), "J")
    vs = [check_trailing(v, (3,), name) for name, v in vectors.items()]
    batch = jnp.broadcast_shapes(J.shape[:-2], *(v.shape[:-1] for v in vs))
    return jnp.broadcast_to(J, batch + (3, 3)), [jnp.broadcast_to(v, batch + (3,)) for v in vs]


def _cholesky(J):
    """The lower Cholesky factor of the symmetric 3×3 `J` (its lower triangle), unrolled:
    `(l00, l10, l11, l20, l21, l22)`."""
    l00 = jnp.sqrt(J[..., 0, 0])
    l10 = J[..., 1, 0] / l00
    l20 = J[..., 2, 0] / l00
    l11 = jnp.sqrt(J[..., 1, 1] - l10 * l10)
    l21 = (J[..., 2, 1] - l20 * l10) / l11
    l22 = jnp.sqrt(J[..., 2, 2] - l20 * l20 - l21 * l21)
    return l00, l10, l11, l20, l21, l22


def _inverse(J):
    """The entries `(a00, a01, a02, a11, a12, a22)` of the symmetric `J⁻¹ = L⁻ᵀ L⁻¹`, `L`
    the Cholesky factor of `J` (`_cholesky`)."""
    l00, l10, l11, l20, l21, l22 = _cholesky(J)
    i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22  # L⁻¹, lower triangular
    i10 = -l10 * i00 * i11
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22
    return (
        i00 * i00 + i10 * i10 + i20 * i20,
        i10 * i11 + i20 * i21,
        i20 * i22,
        i11 * i11 + i21 * i21,
        i21 * i22,
        i22 * i22,
    )


def _times(A, v):
    """The symmetric `A` (`_inverse`'s entries) times the vector `v` (its components):
    each component a three-term sum."""
    a00, a01, a02, a11, a12, a22 = A
    v0, v1, v2 = v
    return [
        a00 * v0 + a01 * v1 + a02 * v2,
        a01 * v0 + a11 * v1 + a12 * v2,
        a02 * v0 + a12 * v1 + a22 * v2,
    ]


@jax.custom_jvp
def _solve(J, b):
    """`J⁻¹ b` for a symmetric positive-definite 3×3 `J` (reads the lower triangle), by the
    six entries of J⁻¹ formed from an unrolled Cholesky factorisation (`_inverse`).
    Elementwise arithmetic only: no LAPACK call per right-hand-side evaluation, which would
    slow a vmapped solve down (the performance page, docs/performance.md). No division
    depends on `b`: where `J` is constant over a solve (a model's own inertia), a compiler
    computes J⁻¹ once, outside the step loop, and each evaluation is nine multiply-adds
    (triangular solves would divide six times, a division costing many multiply-adds on
    a CPU and more on a GPU). Its derivative is `dx = J⁻¹ (db − dJ x)` (`_solve_jvp`)."""
    return jnp.stack(_times(_inverse(J), split(b)), axis=-1)


def _solve_jvp(primals, tangents):
    """`dx = J⁻¹ (db − dJ x)` with the inverse of the solve itself, dJ the symmetric matrix
    of dJ's lower triangle (what `_solve` reads). The factor's own tangents are never
    formed: a sensitivity column per inertia element (`integrate/_sensitivity.py`) costs a
    product with J⁻¹ instead of the derivative of the factorisation, a markedly cheaper
    gradient of a loss w.r.t. the inertia through the lane solver (`benchmarks/gradients.py`
    measures the lane gradient; see the performance page, docs/performance.md)."""
    (J, b), (dJ, db) = primals, tangents
    A = _inverse(J)
    x = _times(A, split(b))
    rhs = None if isinstance(db, SymbolicZero) else split(db)
    if not isinstance(dJ, SymbolicZero):

        def entry(i, j):
            return dJ[..., max(i, j), min(i, j)]

        dJx = [sum(entry(i, j) * x[j] for j in range(3)) for i in range(3)]
        rhs = [-d for d in dJx] if rhs is None else [r - d for r, d in zip(rhs, dJx)]
    return jnp.stack(x, axis=-1), jnp.stack(_times(A, rhs), axis=-1)


_solve.defjvp(_solve_jvp, symbolic_zeros=True)


def euler_rhs(J: MatrixLike, omega: VectorLike, moment: VectorLike) -> Vector:
    """Angular acceleration from Euler's equations `J ω' = J ω × ω + M`.

    Mukhametzyanov (2009), eq. (1); docs/physics.md#eulers-equations.

    For a diagonal `J = diag(A, B, C)` this is `A p' = (B − C) q r + Mx` and cyclic.

    **Arguments:**

    - `J`: `(*batch, 3, 3)` inertia tensor, symmetric positive definite (only its lower
      triangle is read; the models check symmetry and definiteness).
    - `omega`: `(*batch, 3)` absolute angular velocity, body components.
    - `moment`: `(*batch, 3)` external moment about the same point, body components.

    **Returns:** `(*batch, 3)` the body-component derivative `dω/dt`.
    """
    J, (omega, moment) = _prepare(J, {"omega": omega, "moment": moment})
    w = split(omega)
    rhs = [c + m for c, m in zip(cross_parts(matvec_parts(J, w), w), split(moment))]
    return _solve(J, jnp.stack(rhs, axis=-1))


def transport_moment(J: MatrixLike, omega_e: VectorLike, eps_e: VectorLike) -> Vector:
    """Transport inertia moment `M_e = −J ε_e + J ω_e × ω_e`.

    Mukhametzyanov (2009), eq. (2); docs/physics.md#transport-and-coriolis-moments.

    **Arguments:** `J` `(*batch, 3, 3)`; `omega_e`, `eps_e`: the transport frame's absolute
    angular velocity and acceleration, both in body components.
    """
    J, (omega_e, eps_e) = _prepare(J, {"omega_e": omega_e, "eps_e": eps_e})
    w_e = split(omega_e)
    return jnp.stack(
        [
            c - a
            for a, c in zip(matvec_parts(J, split(eps_e)), cross_parts(matvec_parts(J, w_e), w_e))
        ],
        axis=-1,
    )


def coriolis_moment(J: MatrixLike, omega_r: VectorLike, omega_e: VectorLike) -> Vector:
    """Coriolis inertia moment by the compact form: `M_c = 2 ω_r × J' ω_e`.

    The theorem of Mukhametzyanov (2009), eq. (5); docs/physics.md#compact-form.

    Equal to the three-term form `J ω_r × ω_e + J ω_e × ω_r − J (ω_e × ω_r)` of
    Mukhametzyanov (2009), eq. (2), with `J' = ½ tr(J) I − J` the planar inertia tensor
    (docs/physics.md#planar-inertia-tensor).
    """
    J, (omega_r, omega_e) = _prepare(J, {"omega_r": omega_r, "omega_e": omega_e})
    c = cross_parts(split(omega_r), matvec_parts(planar(J), split(omega_e)))
    return jnp.stack([2.0 * ci for ci in c], axis=-1)


def relative_rhs(
    J: MatrixLike,
    omega_r: VectorLike,
    omega_e: VectorLike,
    eps_e: VectorLike,
    moment: VectorLike,
) -> Vector:
    """Relative angular acceleration by the compact form of Euler's equations.

    Mukhametzyanov (2009), eq. (11); docs/physics.md#compact-form:

        J ε_r = J ω_r × ω_r − J ε_e + J ω_e × ω_e + 2 ω_r × J' ω_e + M

    with ε_r the time derivative of the body components of ω_r.

    **Arguments:**

    - `J`: `(*batch, 3, 3)` inertia tensor.
    - `omega_r`: body rate relative to the transport frame O1, body components.
    - `omega_e`, `eps_e`: O1's absolute angular velocity and acceleration, body components
      (`ω_e = R_rᵀ ω_e¹`, `ε_e = R_rᵀ dω_e¹/dt`).
    - `moment`: external moment, body components.

    **Returns:** `(*batch, 3)` `dω_r/dt` in body components.
    """
    J, (omega_r, omega_e, eps_e, moment) = _prepare(
        J, {"omega_r": omega_r, "omega_e": omega_e, "eps_e": eps_e, "moment": moment}
    )
    w_r, w_e = split(omega_r), split(omega_e)
    terms = (
        cross_parts(matvec_parts(J, w_r), w_r),
        matvec_parts(J, split(eps_e)),
        cross_parts(matvec_parts(J, w_e), w_e),
        cross_parts(w_r, matvec_parts(planar(J), w_e)),
        split(moment),
    )
    rhs = [a - b + c + 2.0 * d + m for a, b, c, d, m in zip(*terms)]
    return _solve(J, jnp.stack(rhs, axis=-1))


__all__ = ["coriolis_moment", "euler_rhs", "relative_rhs", "transport_moment"]
