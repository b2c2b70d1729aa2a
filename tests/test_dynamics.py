"""rbdyn_jax.dynamics against independent formulations (docs/physics.md#absolute-motion,
docs/physics.md#relative-motion).

- the principal-axis scalar equations (Mukhametzyanov (2009), eq. (12)) written out by hand,
  rotated to a general frame with scipy rotations (so J has products of inertia);
- the three-term Coriolis moment of Mukhametzyanov (2009), eq. (2), vs the compact theorem,
  eq. (5);
- relative vs absolute motion: ε = ε_r + ε_e + ω_e × ω_r with ε from the absolute
  equations at ω = ω_r + ω_e;
- the energy theorem dT/dt = ω·M, and Euler–Poinsot special cases.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

from rbdyn_jax import dynamics, inertia

# A handful of float64 operations and one 3×3 solve of a well-conditioned J (cond ≲ 10):
# agreement to ~1e-13 is rounding; 1e-11 leaves margin and still catches any sign error.
TOL = 1e-11


def random_body(rng, n=None):
    """(J, C, moments): physical principal moments A ≤ B ≤ C rotated by random axes."""
    shape = () if n is None else (n,)
    m = np.sort(rng.uniform(1.0, 3.0, shape + (3,)), axis=-1)
    m[..., 2] = np.minimum(m[..., 2], m[..., 0] + m[..., 1] - 0.1)  # triangle inequality
    C = Rotation.random(None if n is None else n, random_state=rng).as_matrix()
    J = np.einsum("...ij,...j,...kj->...ik", C, m, C)
    return J, C, m


def principal_euler(m, w, M):
    """A p' = (B − C) q r + Mx and cyclic (docs/physics.md#eulers-equations), by hand."""
    A, B, C = m[..., 0], m[..., 1], m[..., 2]
    p, q, r = w[..., 0], w[..., 1], w[..., 2]
    return np.stack(
        [
            ((B - C) * q * r + M[..., 0]) / A,
            ((C - A) * r * p + M[..., 1]) / B,
            ((A - B) * p * q + M[..., 2]) / C,
        ],
        -1,
    )


def principal_relative(m, w_r, w_e, eps_e, M):
    """Mukhametzyanov (2009), eq. (12), by hand, with planar moments A' = (B + C − A)/2, …"""
    A, B, C = m[..., 0], m[..., 1], m[..., 2]
    Ap, Bp, Cp = (B + C - A) / 2, (C + A - B) / 2, (A + B - C) / 2
    p, q, r = w_r[..., 0], w_r[..., 1], w_r[..., 2]
    pe, qe, re = w_e[..., 0], w_e[..., 1], w_e[..., 2]
    ex, ey, ez = eps_e[..., 0], eps_e[..., 1], eps_e[..., 2]
    dp = (
        (B - C) * q * r - A * ex + (B - C) * qe * re + 2 * (Cp * q * re - Bp * r * qe) + M[..., 0]
    ) / A
    dq = (
        (C - A) * r * p - B * ey + (C - A) * re * pe + 2 * (Ap * r * pe - Cp * p * re) + M[..., 1]
    ) / B
    dr = (
        (A - B) * p * q - C * ez + (A - B) * pe * qe + 2 * (Bp * p * qe - Ap * q * pe) + M[..., 2]
    ) / C
    return np.stack([dp, dq, dr], -1)


def to_principal(C, v):
    return np.einsum("...ji,...j->...i", C, v)


def to_body(C, v):
    return np.einsum("...ij,...j->...i", C, v)


def test_euler_rhs_matches_principal_form_in_a_general_frame(rng):
    J, C, m = random_body(rng, 50)
    w, M = rng.normal(size=(2, 50, 3))
    ours = dynamics.euler_rhs(J, w, M)
    ref = to_body(C, principal_euler(m, to_principal(C, w), to_principal(C, M)))
    np.testing.assert_allclose(ours, ref, atol=TOL)


def test_euler_rhs_energy_and_momentum_theorems(rng):
    J, _, _ = random_body(rng, 50)
    w, M = rng.normal(size=(2, 50, 3))
    wdot = np.asarray(dynamics.euler_rhs(J, w, M))
    # dT/dt = ωᵀ J ω' = ω · M  (the gyroscopic term does no work)
    np.testing.assert_allclose(np.einsum("ni,nij,nj->n", w, J, wdot), np.sum(w * M, -1), atol=TOL)
    # torque-free: d|L|²/dt = 2 L · (J ω') = 2 L · (L × ω) = 0
    wdot0 = np.asarray(dynamics.euler_rhs(J, w, np.zeros_like(w)))
    L = np.einsum("nij,nj->ni", J, w)
    np.testing.assert_allclose(np.sum(L * np.einsum("nij,nj->ni", J, wdot0), -1), 0.0, atol=TOL)


def test_euler_poinsot_special_cases():
    """docs/physics.md#torque-free-motion: spherical body keeps ω; symmetric body keeps r and
    (p, q) turns at (C − A) r / A in the body."""
    w = jnp.array([0.3, -0.7, 1.9])
    np.testing.assert_allclose(dynamics.euler_rhs(2.5 * jnp.eye(3), w, jnp.zeros(3)), 0.0, atol=TOL)
    A, Cm = 2.0, 3.5
    wdot = np.asarray(dynamics.euler_rhs(jnp.diag(jnp.array([A, A, Cm])), w, jnp.zeros(3)))
    lam = (Cm - A) * w[2] / A
    np.testing.assert_allclose(wdot, [-lam * w[1], lam * w[0], 0.0], atol=TOL)


def test_coriolis_theorem_equals_three_term_form(rng):
    """Mukhametzyanov (2009), eq. (5): J ω_r × ω_e + J ω_e × ω_r − J (ω_e × ω_r) = 2 ω_r × J'
    ω_e."""
    J, _, _ = random_body(rng, 50)
    w_r, w_e = rng.normal(size=(2, 50, 3))
    Jw_r, Jw_e = np.einsum("nij,nj->ni", J, w_r), np.einsum("nij,nj->ni", J, w_e)
    three = (
        np.cross(Jw_r, w_e) + np.cross(Jw_e, w_r) - np.einsum("nij,nj->ni", J, np.cross(w_e, w_r))
    )
    np.testing.assert_allclose(dynamics.coriolis_moment(J, w_r, w_e), three, atol=TOL)


def test_transport_moment_by_hand(rng):
    J, _, _ = random_body(rng, 20)
    w_e, eps_e = rng.normal(size=(2, 20, 3))
    ref = -np.einsum("nij,nj->ni", J, eps_e) + np.cross(np.einsum("nij,nj->ni", J, w_e), w_e)
    np.testing.assert_allclose(dynamics.transport_moment(J, w_e, eps_e), ref, atol=TOL)


def test_relative_rhs_matches_principal_form_eq12(rng):
    J, C, m = random_body(rng, 50)
    w_r, w_e, eps_e, M = rng.normal(size=(4, 50, 3))
    ours = dynamics.relative_rhs(J, w_r, w_e, eps_e, M)
    ref = to_body(C, principal_relative(m, *(to_principal(C, v) for v in (w_r, w_e, eps_e, M))))
    np.testing.assert_allclose(ours, ref, atol=TOL)


def test_relative_rhs_agrees_with_absolute_motion(rng):
    """docs/physics.md#transport-frame: ω = ω_r + ω_e, ε = ε_r + ε_e + ω_e × ω_r, with ε from
    Mukhametzyanov (2009), eq. (1)."""
    J, _, _ = random_body(rng, 50)
    w_r, w_e, eps_e, M = rng.normal(size=(4, 50, 3))
    eps_r = np.asarray(dynamics.relative_rhs(J, w_r, w_e, eps_e, M))
    eps = np.asarray(dynamics.euler_rhs(J, w_r + w_e, M))
    np.testing.assert_allclose(eps_r + eps_e + np.cross(w_e, w_r), eps, atol=TOL)


def test_balanced_transport_conserves_relative_energy(rng):
    """Mukhametzyanov (2009), §4: with M = J ε_e − J ω_e × ω_e, dT_r/dt = ω_rᵀ J ε_r = 0 for any
    transport."""
    J, _, _ = random_body(rng, 50)
    w_r, w_e, eps_e = rng.normal(size=(3, 50, 3))
    M = -np.asarray(dynamics.transport_moment(J, w_e, eps_e))
    eps_r = np.asarray(dynamics.relative_rhs(J, w_r, w_e, eps_e, M))
    np.testing.assert_allclose(np.einsum("ni,nij,nj->n", w_r, J, eps_r), 0.0, atol=TOL)


def test_batching_broadcast_jit_vmap_and_grad(rng):
    J, _, _ = random_body(rng)
    w = rng.normal(size=(4, 5, 3))
    M = rng.normal(size=3)
    batched = dynamics.euler_rhs(J, w, M)  # J and M broadcast against a (4, 5) batch
    assert batched.shape == (4, 5, 3)
    loop = np.stack(
        [[np.asarray(dynamics.euler_rhs(J, w[i, j], M)) for j in range(5)] for i in range(4)]
    )
    np.testing.assert_allclose(batched, loop, atol=1e-14)
    np.testing.assert_allclose(
        jax.jit(dynamics.relative_rhs)(J, w, w[::-1], w, M),
        jax.vmap(dynamics.relative_rhs, (None, 0, 0, 0, None))(J, w, w[::-1], w, M),
        atol=1e-14,
    )
    w1, w2, w3, M1 = rng.normal(size=(4, 3))
    for f, args in [
        (dynamics.euler_rhs, (J, w1, M1)),
        (dynamics.transport_moment, (J, w1, w2)),
        (dynamics.coriolis_moment, (J, w1, w2)),
        (dynamics.relative_rhs, (J, w1, w2, w3, M1)),
    ]:
        check_grads(f, args, order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-5)


def test_solve_derivative_is_the_inverse_rule_on_the_lower_triangle(rng):
    """`_solve(J, b)` reads J's lower triangle, so it solves with A = tril(J) + tril(J, −1)ᵀ,
    and its custom derivative must be dx = A⁻¹ (db − dA x), dA built alike from dJ: an
    upper-triangle perturbation changes nothing. Against numpy's solve, in forward and
    reverse mode, with a perturbation of the whole matrix (not symmetric)."""
    J, _, _ = random_body(rng)
    b, db = rng.normal(size=(2, 3))
    dJ = rng.normal(size=(3, 3))

    def sym_lower(M):
        return np.tril(M) + np.tril(M, -1).T

    x = np.linalg.solve(J, b)
    expected = np.linalg.solve(J, db - sym_lower(dJ) @ x)
    _, dx = jax.jvp(
        dynamics._solve, (jnp.asarray(J), jnp.asarray(b)), (jnp.asarray(dJ), jnp.asarray(db))
    )
    np.testing.assert_allclose(dx, expected, atol=TOL)
    _, dx_upper = jax.jvp(
        lambda J: dynamics._solve(J, jnp.asarray(b)),
        (jnp.asarray(J),),
        (jnp.asarray(np.triu(dJ, 1)),),
    )
    np.testing.assert_allclose(dx_upper, 0.0, atol=TOL)
    # reverse mode transposes the same rule: ⟨c, dx⟩ for every (dJ, db)
    c = rng.normal(size=3)
    gJ, gb = jax.grad(lambda J, b: jnp.dot(jnp.asarray(c), dynamics._solve(J, b)), argnums=(0, 1))(
        jnp.asarray(J), jnp.asarray(b)
    )
    np.testing.assert_allclose(np.sum(gJ * dJ) + np.dot(gb, db), np.dot(c, expected), atol=TOL)


def test_written_out_solve_matches_numpy(rng):
    """The component-wise `J⁻¹ b` against numpy on a batch of symmetric positive-definite
    matrices: a wrong index or sign in the written-out arithmetic shows at round-off level.
    (The written-out `J v` and `a × b` it shares with the torques: tests/test_vector.py.)"""
    M = rng.normal(size=(5, 3, 3))
    a = rng.normal(size=(5, 3))
    J = np.einsum("nij,nkj->nik", M, M) + np.eye(3)  # symmetric positive definite
    # cond(J) is small here: 1e-12 is ~1e4 ulps of slack for the factor, its inverse and
    # the product.
    np.testing.assert_allclose(
        dynamics._solve(jnp.asarray(J), jnp.asarray(a)),
        np.linalg.solve(J, a[..., None])[..., 0],
        rtol=1e-12,
        atol=1e-13,
    )


@pytest.mark.parametrize("cond", [1e2, 1e5, 1e8])
def test_solve_is_as_accurate_as_the_conditioning_allows(rng, cond):
    """`J⁻¹ b` by J⁻¹'s entries (from the Cholesky factor) for needle-like bodies, principal
    moments (1/cond, 1, 1 + 1/cond) in random axes (scipy's `Rotation`): its error relative
    to |x| stays within cond(J)·ε, the bound of a backward-stable solve (LAPACK's, numpy's,
    meets it too), for every direction of b. An inverse formed badly (an unstable formula,
    a wrong entry) loses digits beyond it."""
    eps = np.finfo(np.float64).eps
    R = Rotation.random(100, random_state=rng).as_matrix()
    J = R @ np.diag([1.0 / cond, 1.0, 1.0 + 1.0 / cond]) @ R.transpose(0, 2, 1)
    b = rng.normal(size=(100, 3))
    x = np.linalg.solve(J, b[..., None])[..., 0]
    err = np.abs(np.asarray(dynamics._solve(jnp.asarray(J), jnp.asarray(b))) - x).max(axis=-1)
    # measured: at most 0.5 cond ε over these bodies
    assert np.all(err <= 2 * cond * eps * np.abs(x).max(axis=-1))


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="`J`"):
        dynamics.euler_rhs(jnp.eye(2), jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="`omega_e`"):
        dynamics.relative_rhs(jnp.eye(3), jnp.zeros(3), jnp.zeros(4), jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(ValueError, match="`moment`"):
        dynamics.euler_rhs(jnp.eye(3), jnp.zeros(3), jnp.zeros((2, 2)))


def test_inertia_planar_is_the_one_used(rng):
    """The Coriolis theorem uses J' of docs/physics.md#planar-inertia-tensor (shared with
    rbdyn_jax.inertia)."""
    J, _, _ = random_body(rng)
    w_r, w_e = rng.normal(size=(2, 3))
    np.testing.assert_allclose(
        dynamics.coriolis_moment(J, w_r, w_e),
        2 * np.cross(w_r, np.asarray(inertia.planar(J)) @ w_e),
        atol=TOL,
    )
