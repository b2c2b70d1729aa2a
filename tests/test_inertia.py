"""Tests of rbdyn_jax.inertia against independent NumPy/SciPy computations
(docs/physics.md#inertia).

Tolerances: identities that only reorder a few float64 roundings are checked at 1e-12 relative
to the scale of the data; eigen-decompositions at 1e-12 (LAPACK is backward stable and the test
spectra are well separated); finite-difference gradients at 1e-5 (central differences, step
~1e-4 in float64, truncation error O(step²)); float32 against float64 at 1e-4 (eps32 ≈ 1.2e-7
amplified by the conditioning of eigh/Cholesky on the test data).
"""

import equinox as eqx
import hypothesis.extra.numpy as hnp
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from helpers import random_rotation_matrices
from hypothesis import given, settings
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

from rbdyn_jax import inertia
from rbdyn_jax._checks import holds_now

EPS64 = np.finfo(np.float64).eps
# Central finite differences with JAX's default step (≈1e-4 in float64): error O(step²).
FD_TOL = 1e-5
HYP = settings(deadline=None, max_examples=40)
# One batch size for the batched tests: eager ops compile once per shape, so reuse it.
N = 32


def random_cloud(rng, n=7, batch=()):
    masses = rng.uniform(0.1, 2.0, batch + (n,))
    positions = rng.normal(size=batch + (n, 3))
    return masses, positions


def hand_inertia(masses, positions):
    """J by the component sums of docs/physics.md#inertia-tensor, one NumPy loop over points
    (independent)."""
    J = np.zeros((3, 3))
    for m, (x, y, z) in zip(masses, positions, strict=True):
        J[0, 0] += m * (y**2 + z**2)
        J[1, 1] += m * (z**2 + x**2)
        J[2, 2] += m * (x**2 + y**2)
        J[0, 1] -= m * x * y
        J[0, 2] -= m * x * z
        J[1, 2] -= m * y * z
    J[1, 0], J[2, 0], J[2, 1] = J[0, 1], J[0, 2], J[1, 2]
    return J


def random_physical(rng, batch=()):
    """Generic physical J (distinct moments) from a random point cloud."""
    masses, positions = random_cloud(rng, batch=batch)
    return np.array(inertia.from_point_masses(masses, positions))


def sym(x):
    return 0.5 * (x + jnp.swapaxes(x, -1, -2))


def cayley(a):
    """An exactly orthogonal matrix (to rounding) from 3 parameters, for gradients w.r.t. axes."""
    z = jnp.zeros_like(a[0])
    S = jnp.array([[z, -a[2], a[1]], [a[2], z, -a[0]], [-a[1], a[0], z]])
    eye = jnp.eye(3, dtype=a.dtype)
    return jnp.linalg.solve(eye - S, eye + S)


# ---------------------------------------------------------------- point masses, parallel axes


def test_point_masses_equal_hand_sums(rng):
    masses, positions = random_cloud(rng)
    J = inertia.from_point_masses(masses, positions)
    # Same few products and sums in another order: rounding only.
    np.testing.assert_allclose(J, hand_inertia(masses, positions), rtol=0, atol=1e-12)


def test_point_masses_about_a_point_equals_shifted_positions(rng):
    masses, positions = random_cloud(rng)
    about = rng.normal(size=3)
    J = inertia.from_point_masses(masses, positions, about)
    np.testing.assert_allclose(J, hand_inertia(masses, positions - about), rtol=0, atol=1e-12)


def test_parallel_axis_theorem(rng):
    masses, positions = random_cloud(rng)
    M = masses.sum()
    c = masses @ positions / M
    J_cm = inertia.from_point_masses(masses, positions, about=c)
    J_O = inertia.from_point_masses(masses, positions)
    shift = M * (c @ c * np.eye(3) - np.outer(c, c))
    # Identity up to rounding of O(10) sums.
    np.testing.assert_allclose(J_O, np.asarray(J_cm) + shift, rtol=0, atol=1e-12)


def test_point_masses_negative_mass_raises(rng):
    masses, positions = random_cloud(rng)
    masses[2] = -1.0
    with pytest.raises(eqx.EquinoxRuntimeError, match="`masses` must be non-negative"):
        jax.block_until_ready(inertia.from_point_masses(masses, positions))


# ---------------------------------------------------------------- planar inertia


def test_planar_of_point_masses_is_sum_m_r_rT(rng):
    masses, positions = random_cloud(rng)
    Jp_direct = np.einsum("n,ni,nj->ij", masses, positions, positions)
    Jp = inertia.planar(inertia.from_point_masses(masses, positions))
    np.testing.assert_allclose(Jp, Jp_direct, rtol=0, atol=1e-12)


def test_planar_round_trip(rng):
    A = rng.normal(size=(N, 3, 3))  # a linear identity: holds for any matrix
    np.testing.assert_allclose(inertia.from_planar(inertia.planar(A)), A, rtol=0, atol=1e-14)
    np.testing.assert_allclose(inertia.planar(inertia.from_planar(A)), A, rtol=0, atol=1e-14)
    # Independent formula: J' = ½ tr(J) I − J.
    J = A[0]
    np.testing.assert_allclose(inertia.planar(J), 0.5 * np.trace(J) * np.eye(3) - J, atol=1e-15)


def test_principal_planar_moments(rng):
    A, B, C = 2.0, 3.0, 4.5
    R = random_rotation_matrices(rng, 1)[0]
    Jp = np.asarray(inertia.planar(inertia.from_principal(np.array([A, B, C]), R)))
    in_principal = R.T @ Jp @ R
    expect = np.diag([(B + C - A) / 2, (C + A - B) / 2, (A + B - C) / 2])
    np.testing.assert_allclose(in_principal, expect, rtol=0, atol=1e-12)


# ---------------------------------------------------------------- principal axes


def test_principal_axes_decomposition(rng):
    J = random_physical(rng, batch=(N,))
    moments, C = inertia.principal_axes(J)
    moments, C = np.asarray(moments), np.asarray(C)
    # Independent eigenvalues from SciPy's LAPACK driver.
    ref = np.stack([scipy.linalg.eigh(j, eigvals_only=True) for j in J])
    np.testing.assert_allclose(moments, ref, rtol=1e-12)
    assert np.all(np.diff(moments, axis=-1) > 0)
    np.testing.assert_allclose(
        C.swapaxes(-1, -2) @ C, np.broadcast_to(np.eye(3), C.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(C), 1.0, atol=1e-12)
    recon = C @ (moments[..., :, None] * C.swapaxes(-1, -2))
    np.testing.assert_allclose(recon, J, atol=1e-12 * np.abs(J).max())
    np.testing.assert_allclose(J @ C, C * moments[..., None, :], atol=1e-12 * np.abs(J).max())


def test_principal_axes_handedness_fix(rng):
    J = random_physical(rng, batch=(N,))
    # jnp.linalg.eigh returns improper bases (det = −1) for some of these.
    raw_det = np.linalg.det(np.asarray(jnp.linalg.eigh(J)[1]))
    assert np.any(raw_det < 0) and np.any(raw_det > 0)  # both branches exercised
    _, C = inertia.principal_axes(J)
    C = np.asarray(C)
    np.testing.assert_allclose(np.linalg.det(C), 1.0, atol=1e-12)
    # Only the last column's sign changes, and only where eigh's basis was improper.
    C_raw = np.asarray(jnp.linalg.eigh(J)[1])
    np.testing.assert_array_equal(C[..., :2], C_raw[..., :2])
    np.testing.assert_array_equal(C[..., 2], np.sign(raw_det)[:, None] * C_raw[..., 2])


def test_from_principal_matches_numpy_and_round_trips(rng):
    moments = np.sort(rng.uniform(1.0, 2.0, (N, 3)), axis=-1)  # triangle inequalities hold
    R = random_rotation_matrices(rng, N)
    J = np.asarray(inertia.from_principal(moments, R))
    np.testing.assert_allclose(J, np.einsum("bij,bj,bkj->bik", R, moments, R), atol=1e-14)
    np.testing.assert_allclose(
        inertia.from_principal(moments), np.stack([np.diag(m) for m in moments]), atol=0
    )
    m2, C2 = inertia.principal_axes(J)
    np.testing.assert_allclose(m2, moments, rtol=1e-12)
    np.testing.assert_allclose(inertia.from_principal(m2, C2), J, atol=1e-12)


def test_from_principal_rejects_non_orthonormal_axes(rng):
    R = random_rotation_matrices(rng, 1)[0] * 1.001
    with pytest.raises(eqx.EquinoxRuntimeError, match="`axes` must be orthonormal"):
        jax.block_until_ready(inertia.from_principal(np.array([1.0, 2.0, 2.5]), R))


def test_ellipsoid_semi_axes(rng):
    J = random_physical(rng)
    lengths, C = inertia.ellipsoid_semi_axes(J)
    # Each semi-axis endpoint ρ = length · axis lies on ρᵀ J ρ = 1.
    rho = np.asarray(C) * np.asarray(lengths)[None, :]
    np.testing.assert_allclose(np.einsum("ik,ij,jk->k", rho, J, rho), 1.0, rtol=1e-12)


# ---------------------------------------------------------------- physical consistency


@pytest.mark.parametrize(
    "moments",
    [(1.0, 1.0, 2.0), (1.0, 2.0, 3.0), (1.0, 1.0, 0.0), (0.0, 0.0, 0.0), (3.0, 3.0, 3.0)],
    ids=["lamina", "lamina-asym", "rod", "zero", "sphere"],
)
def test_boundary_cases_are_physical(moments, rng):
    R = random_rotation_matrices(rng, 1)[0]
    J = inertia.from_principal(np.array(moments), R)
    assert bool(inertia.is_physical(J))
    np.testing.assert_array_equal(inertia.check_inertia(J), J)


@pytest.mark.parametrize(
    "moments", [(1.0, 1.0, 3.0), (1.0, 2.0, 3.1), (-1.0, 2.0, 2.0), (-1.0, -1.0, -1.0)]
)
def test_triangle_violators_rejected(moments, rng):
    R = random_rotation_matrices(rng, 1)[0]
    J = R @ np.diag(moments) @ R.T
    assert not bool(inertia.is_physical(J))
    with pytest.raises(
        eqx.EquinoxRuntimeError,
        match="`J_body` is not physical .*A \\+ B ≥ C.*docs/physics\\.md#physical-consistency",
    ):
        jax.block_until_ready(inertia.check_inertia(J, name="J_body"))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`moments` is not physical"):
        jax.block_until_ready(inertia.from_principal(np.array(moments), R))


def test_just_outside_tolerance_rejected():
    # A + B − C = −1e-6 relative: far beyond √eps ≈ 1.5e-8, so unphysical.
    assert not bool(inertia.is_physical(np.diag([1.0, 1.0, 2.0 + 2e-6])))
    assert bool(inertia.is_physical(np.diag([1.0, 1.0, 2.0 + 1e-12])))


def test_non_symmetric_rejected():
    J = np.diag([1.0, 2.0, 2.5])
    J[0, 1] = 0.1
    assert not bool(inertia.is_physical(J))
    with pytest.raises(eqx.EquinoxRuntimeError, match="`inertia` is not symmetric"):
        jax.block_until_ready(inertia.check_inertia(J))
    J_nan = np.diag([1.0, np.nan, 2.5])
    assert not bool(inertia.is_physical(J_nan))


def test_check_inertia_under_jit_and_batch(rng):
    J = random_physical(rng, batch=(N,))
    check = eqx.filter_jit(inertia.check_inertia)
    np.testing.assert_array_equal(check(J), J)
    J[2] = np.diag([1.0, 1.0, 3.0])  # one bad element fails the batch
    np.testing.assert_array_equal(inertia.is_physical(J), np.arange(N) != 2)
    with pytest.raises(eqx.EquinoxRuntimeError, match="`inertia` is not physical"):
        jax.block_until_ready(check(J))


def test_is_physical_matches_eigen_criterion(rng):
    # Random symmetric matrices, about half physical: compare with the triangle inequalities
    # on NumPy eigenvalues (avoid near-boundary draws, where √eps tolerance decides).
    S = rng.normal(size=(N, 3, 3))
    S = S @ S.swapaxes(-1, -2) + rng.normal(size=(N, 1, 1)) * np.eye(3)
    lam = np.linalg.eigvalsh(S)
    margin = (lam.sum(-1, keepdims=True) - 2 * lam).min(-1)
    keep = np.abs(margin) > 1e-6
    ref = margin[keep] >= 0
    assert 0 < ref.sum() < ref.size
    np.testing.assert_array_equal(np.asarray(inertia.is_physical(S))[keep], ref)


def test_concrete_check_in_numpy_decides_as_the_jax_check(rng):
    """A concrete J is checked in NumPy (`holds_now(_physical, J)`: nothing compiled), a
    traced one in JAX; both run the same code, `_physical(J, xp)`. They must decide alike,
    also near the √eps tolerances of symmetry and of the triangle inequality: margins of
    ½ and 2 tolerances, far from the ~1e-16 relative rounding where LAPACK builds differ."""
    tol = float(np.sqrt(EPS64))
    R = random_rotation_matrices(rng, N)
    a, b = rng.uniform(0.5, 2.0, (2, N))

    def rotated(c):
        J = R @ (np.stack([a, b, c], -1)[..., None] * np.eye(3)) @ R.swapaxes(-1, -2)
        return 0.5 * (J + J.swapaxes(-1, -2))

    scale = np.abs(rotated(a + b)).max((-2, -1))  # max|J| on the triangle boundary C = a + b
    # J' has the eigenvalue (A + B − C)/2 = −m·tol·max|J|: physical iff m ≤ 1.
    m = np.resize([-2.0, -0.5, 0.5, 2.0], N)
    J = rotated(a + b + 2.0 * m * tol * scale)
    k = np.resize(np.repeat([0.0, 0.5, 2.0, 0.0], 4), N)  # max|J − Jᵀ| = k·tol·max|J|
    J[:, 0, 1] += k * tol * scale
    expect = (m <= 1.0) & (k <= 1.0)
    assert 0 < expect.sum() < N
    np.testing.assert_array_equal(inertia._physical(J, np), expect)
    np.testing.assert_array_equal(np.asarray(jax.jit(inertia.is_physical)(J)), expect)
    np.testing.assert_array_equal(np.asarray(inertia.is_physical(J)), expect)
    for J1, ok in zip(J[:8], expect[:8], strict=True):
        assert holds_now(inertia._physical, jnp.asarray(J1)) == ok


def test_holds_now_evaluates_concrete_values_in_numpy():
    seen = []

    def positive(x, xp):
        seen.append((xp, type(x)))
        return x > 0

    assert holds_now(positive, jnp.array([1.0, 2.0]))
    assert not holds_now(positive, jnp.array([1.0, -2.0]))
    assert seen == [(np, np.ndarray)] * 2
    assert not holds_now(positive, np.array([1.0, np.inf]))  # not finite: not evaluated
    assert jax.jit(lambda x: jnp.asarray(holds_now(positive, x)))(jnp.ones(2)) == False  # noqa: E712
    assert len(seen) == 2  # a traced argument is never evaluated


# ---------------------------------------------------------------- log-Cholesky


@jax.jit  # compiled once for all hypothesis examples
def _log_cholesky_round_trip(theta):
    J = inertia.from_log_cholesky(theta)
    return J, inertia.is_physical(J), inertia.to_log_cholesky(J)


@HYP
@given(theta=hnp.arrays(np.float64, (6,), elements=st.floats(-3.0, 3.0)))
def test_log_cholesky_every_theta_physical_and_round_trips(theta):
    J, physical, back = _log_cholesky_round_trip(theta)
    assert bool(physical)
    # Recovering L from J loses ≈ eps · cond(J'): at the corners of the box J' has eigenvalues
    # from ~2e-10 to ~5e2 (cond ~1e12, error ~1e-5 there); measured max ≈ 3 eps cond, allow 30.
    lam = np.linalg.eigvalsh(np.asarray(inertia.planar(J)))
    tol = 30 * EPS64 * lam[-1] / lam[0] + 1e-13
    np.testing.assert_allclose(back, theta, rtol=0, atol=tol)


@HYP
@given(theta=hnp.arrays(np.float64, (6,), elements=st.floats(-1.0, 1.0)))
def test_log_cholesky_round_trip_well_conditioned(theta):
    # In [-1, 1]⁶ cond(J') ≤ ~3e3, so eps · cond ≲ 1e-12: the round trip holds to 1e-12.
    _, physical, back = _log_cholesky_round_trip(theta)
    assert bool(physical)
    np.testing.assert_allclose(back, theta, rtol=0, atol=1e-12)


def test_log_cholesky_of_random_physical_round_trips(rng):
    J = random_physical(rng, batch=(N,))
    theta = inertia.to_log_cholesky(J)
    assert theta.shape == (N, 6)
    np.testing.assert_allclose(inertia.from_log_cholesky(theta), J, atol=1e-12 * np.abs(J).max())
    # Ordering (log L00, log L11, log L22, L10, L20, L21) against NumPy's Cholesky of J'.
    L = np.linalg.cholesky(np.asarray(inertia.planar(J)))
    ref = np.concatenate(
        [np.log(np.diagonal(L, axis1=-2, axis2=-1)), L[:, 1, :1], L[:, 2, :2]], axis=-1
    )
    np.testing.assert_allclose(theta, ref, atol=1e-12)


def test_planar_eager_equals_jitted_bit_for_bit(rng):
    """A concrete `planar` (and `is_physical`) computes as a traced one does, in one JAX
    program: eager, jitted and closed-over calls give the same J' bit for bit, in the
    input's dtype."""
    for dtype in (np.float64, np.float32):
        J = jnp.asarray(random_physical(rng, batch=(N,)), dtype)
        Jp = inertia.planar(J)
        assert Jp.dtype == dtype
        np.testing.assert_array_equal(Jp, jax.jit(inertia.planar)(J))
        seen = []

        def f(x, J=J, seen=seen):
            seen.append(inertia.planar(J))  # closed over: concrete in the trace
            return x

        jax.make_jaxpr(f)(1.0)
        assert not isinstance(seen[0], jax.core.Tracer)
        np.testing.assert_array_equal(seen[0], Jp)


def test_is_physical_eager_equals_jitted_at_the_edge(rng):
    """A concrete `is_physical` decides as a traced one does, also about its tolerance's
    edge: J' with planar moments (a, b, −k·tol), tol = √eps·max|J|, in random axes, for k
    across 1, where both answers occur."""
    R = Rotation.random(N, random_state=rng).as_matrix()
    moments = np.concatenate([rng.uniform(0.5, 2.0, (N, 2)), np.zeros((N, 1))], axis=1)
    flat = np.einsum("nij,nj,nkj->nik", R, moments, R)  # J' ⪰ 0, singular along R[:, :, 2]
    vvT = R[:, :, 2, None] * R[:, None, :, 2]
    size = np.abs(np.asarray(inertia.from_planar(flat))).max(axis=(-2, -1))[:, None, None]
    for dtype in (np.float64, np.float32):
        tol = np.sqrt(np.finfo(dtype).eps) * size
        answers = set()
        for k in np.linspace(0.5, 2.0, 16):
            K = jnp.asarray(inertia.from_planar(flat - k * tol * vvT), dtype)
            eager = inertia.is_physical(K)
            np.testing.assert_array_equal(eager, jax.jit(inertia.is_physical)(K))
            answers |= set(np.asarray(eager).tolist())
        assert answers == {True, False}


def test_log_cholesky_eager_equals_jitted_bit_for_bit(rng):
    """Concrete `to_log_cholesky` / `from_log_cholesky` compute as traced ones do, in one JAX
    program (not NumPy, nor JAX operation by operation): eager and jitted calls give the
    same θ and J bit for bit, in the input's dtype, one inertia at a time and batched; a
    concrete input inside a caller's trace is computed now, as an eager call."""
    for dtype in (np.float64, np.float32):
        for J in [*random_physical(rng, batch=(4,)), random_physical(rng, batch=(N,))]:
            Jd = jnp.asarray(J, dtype)
            theta = inertia.to_log_cholesky(Jd)
            assert theta.dtype == dtype and theta.shape == Jd.shape[:-2] + (6,)
            np.testing.assert_array_equal(theta, jax.jit(inertia.to_log_cholesky)(Jd))
            back = inertia.from_log_cholesky(theta)
            assert back.dtype == dtype
            np.testing.assert_array_equal(back, jax.jit(inertia.from_log_cholesky)(theta))
    seen = []

    def f(x):
        theta = inertia.to_log_cholesky(J)  # closed over: concrete
        back = inertia.from_log_cholesky(theta)
        seen.extend([theta, back])
        return x + theta.sum() + back.sum()

    jax.make_jaxpr(f)(1.0)
    assert not any(isinstance(a, jax.core.Tracer) for a in seen)
    np.testing.assert_array_equal(seen[0], inertia.to_log_cholesky(J))
    np.testing.assert_array_equal(seen[1], inertia.from_log_cholesky(seen[0]))


@pytest.mark.parametrize("moments", [(1.0, 1.0, 2.0), (1.0, 1.0, 0.0)], ids=["lamina", "rod"])
def test_log_cholesky_rejects_singular_planar(moments):
    with pytest.raises(eqx.EquinoxRuntimeError, match="no finite log-Cholesky"):
        jax.block_until_ready(inertia.to_log_cholesky(np.diag(moments)))


def test_log_cholesky_rejects_unphysical():
    with pytest.raises(eqx.EquinoxRuntimeError, match="`J` is not physical"):
        jax.block_until_ready(inertia.to_log_cholesky(np.diag([1.0, 1.0, 3.0])))


# ---------------------------------------------------------------- energy, momentum, moment


def test_energy_momentum_moment_vs_numpy(rng):
    J = random_physical(rng, batch=(N,))
    omega = rng.normal(size=(N, 3))
    axis = rng.normal(size=(N, 3)) * 3.0
    L = np.einsum("bij,bj->bi", J, omega)
    T = 0.5 * np.einsum("bi,bij,bj->b", omega, J, omega)
    n = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    I_n = np.einsum("bi,bij,bj->b", n, J, n)
    np.testing.assert_allclose(inertia.angular_momentum(J, omega), L, rtol=1e-13)
    np.testing.assert_allclose(inertia.kinetic_energy(J, omega), T, rtol=1e-13)
    np.testing.assert_allclose(inertia.moment_about(J, axis), I_n, rtol=1e-13)
    # T = ½ L·ω, both from the library.
    T_lib = inertia.kinetic_energy(J, omega)
    L_lib = np.asarray(inertia.angular_momentum(J, omega))
    np.testing.assert_allclose(0.5 * np.sum(L_lib * omega, -1), T_lib, rtol=1e-13)


def test_moment_about_principal_axes_and_point_masses(rng):
    J = random_physical(rng)
    moments, C = inertia.principal_axes(J)
    got = inertia.moment_about(np.broadcast_to(J, (3, 3, 3)), np.asarray(C).T)
    np.testing.assert_allclose(got, moments, rtol=1e-12)
    # Σ m d² with d the distance of each point from the axis through O.
    masses, positions = random_cloud(rng)
    n = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    d2 = np.sum(positions**2, -1) - (positions @ n) ** 2
    got = inertia.moment_about(inertia.from_point_masses(masses, positions), n * 7.0)
    np.testing.assert_allclose(got, masses @ d2, rtol=1e-12)


def test_moment_about_zero_axis_raises():
    with pytest.raises(eqx.EquinoxRuntimeError, match="`axis` must be non-zero"):
        jax.block_until_ready(inertia.moment_about(np.eye(3), np.zeros(3)))


# ---------------------------------------------------------------- jit, vmap, batches


def test_mixed_batch_ranks_broadcast(rng):
    # Unbatched arguments broadcast against batched ones (ranks made explicit internally, so
    # this works under jax_numpy_rank_promotion="raise").
    J = random_physical(rng, batch=(N,))
    w = rng.normal(size=3)
    np.testing.assert_allclose(inertia.kinetic_energy(J, w), 0.5 * J @ w @ w, rtol=1e-13)
    np.testing.assert_allclose(inertia.moment_about(J, w), J @ w @ w / (w @ w), rtol=1e-13)
    ws = rng.normal(size=(N, 3))
    np.testing.assert_allclose(inertia.angular_momentum(J[0], ws), ws @ J[0].T, rtol=1e-13)
    R = random_rotation_matrices(rng, N)
    moments = np.array([1.0, 1.5, 2.0])
    np.testing.assert_allclose(
        inertia.from_principal(moments, R), R @ np.diag(moments) @ R.swapaxes(-1, -2), atol=1e-14
    )
    masses, positions = random_cloud(rng, batch=(N,))
    about = rng.normal(size=3)
    ref = np.stack([hand_inertia(m, p - about) for m, p in zip(masses, positions, strict=True)])
    np.testing.assert_allclose(inertia.from_point_masses(masses, positions, about), ref, atol=1e-12)
    ref = np.stack([hand_inertia(masses[0], p) for p in positions])
    np.testing.assert_allclose(inertia.from_point_masses(masses[0], positions), ref, atol=1e-12)
    abouts = rng.normal(size=(N, 3))
    ref = np.stack([hand_inertia(masses[0], positions[0] - a) for a in abouts])
    np.testing.assert_allclose(
        inertia.from_point_masses(masses[0], positions[0], abouts), ref, atol=1e-12
    )


def _inputs(rng, batch):
    """Inputs of every public function, with leading axes `batch`."""
    masses, positions = random_cloud(rng, n=4, batch=batch)
    R = random_rotation_matrices(rng, int(np.prod(batch))).reshape(batch + (3, 3))
    return dict(
        J=random_physical(rng, batch=batch),
        omega=rng.normal(size=batch + (3,)),
        masses=masses,
        positions=positions,
        moments=rng.uniform(1.0, 2.0, batch + (3,)),
        R=R,
        theta=rng.uniform(-1.0, 1.0, batch + (6,)),
    )


@jax.jit  # one program for all functions: one compilation per input shape and dtype
def _all_outputs(x):
    """Every public function on the inputs of `_inputs` (a dict of outputs)."""
    J, omega = x["J"], x["omega"]
    _, C = inertia.principal_axes(J)
    return dict(
        from_principal=inertia.from_principal(x["moments"], x["R"]),
        from_point_masses=inertia.from_point_masses(x["masses"], x["positions"], omega),
        planar=inertia.planar(J),
        from_planar=inertia.from_planar(J),
        principal_moments=inertia.principal_axes(J)[0],
        # C diag(1, 2, 3) Cᵀ: independent of each column's sign convention.
        principal_axes=jnp.einsum("...ik,k,...jk->...ij", C, jnp.arange(1, 4, dtype=J.dtype), C),
        det_axes=jnp.linalg.det(C),
        ellipsoid_semi_axes=inertia.ellipsoid_semi_axes(J)[0],
        moment_about=inertia.moment_about(J, omega),
        kinetic_energy=inertia.kinetic_energy(J, omega),
        angular_momentum=inertia.angular_momentum(J, omega),
        is_physical=inertia.is_physical(J),
        check_inertia=inertia.check_inertia(J),
        to_log_cholesky=inertia.to_log_cholesky(J),
        from_log_cholesky=inertia.from_log_cholesky(x["theta"]),
    )


def test_batch_equals_loop_and_vmap(rng):
    x = _inputs(rng, (2, 5))
    out = _all_outputs(x)  # batched (2, 5, ...)
    loop = [_all_outputs(jax.tree.map(lambda a, i=i: a[i // 5, i % 5], x)) for i in range(10)]
    vmapped = jax.jit(jax.vmap(jax.vmap(_all_outputs)))(x)
    for name, value in out.items():
        assert value.shape[:2] == (2, 5), name
        looped = np.stack([np.asarray(o[name]) for o in loop]).reshape(value.shape)
        # Same arithmetic per element (XLA may fuse or order it differently): 1e-12.
        np.testing.assert_allclose(value, looped, rtol=1e-12, atol=1e-13, err_msg=name)
        np.testing.assert_allclose(vmapped[name], value, rtol=1e-12, atol=1e-13, err_msg=name)
    np.testing.assert_allclose(out["det_axes"], 1.0, atol=1e-12)


def test_float32_preserved(rng):
    x = _inputs(rng, (2, 5))  # the float64 program is shared with the batch test
    out64 = _all_outputs(x)
    out32 = _all_outputs(jax.tree.map(lambda a: np.asarray(a, np.float32), x))
    for name, value in out32.items():
        if name == "is_physical":
            assert value.dtype == jnp.bool_ and bool(value.all())
            continue
        assert value.dtype == jnp.float32, name
        # float32 rounding (eps ≈ 1.2e-7) amplified by at most a few hundred in eigh/cholesky.
        np.testing.assert_allclose(value, out64[name], rtol=1e-4, atol=1e-4, err_msg=name)


# ---------------------------------------------------------------- gradients


def _grad_cases(rng):
    """(name, function, args) at generic points, one per public differentiable function."""
    moments = np.array([1.0, 1.6, 2.1])
    R = random_rotation_matrices(rng, 1)[0]
    masses, positions = random_cloud(rng, n=4)
    J0 = random_physical(rng)  # generic: distinct moments
    A = rng.normal(size=(3, 3))
    omega = rng.normal(size=3)
    W = np.diag([1.0, 2.0, 3.0])

    def axes_invariant(J):
        # C W Cᵀ does not depend on the sign convention of each eigenvector column.
        _, C = inertia.principal_axes(J)
        return C @ W @ C.T

    X0 = np.zeros((3, 3))
    return [
        ("from_principal/moments", lambda m: inertia.from_principal(m, R), (moments,)),
        # Along orthogonal directions of the axes (Cayley parameters), which stay orthonormal.
        (
            "from_principal/axes",
            lambda a: inertia.from_principal(moments, R @ cayley(a)),
            (np.zeros(3),),
        ),
        ("from_point_masses", inertia.from_point_masses, (masses, positions, omega)),
        ("planar", inertia.planar, (A,)),
        ("from_planar", inertia.from_planar, (A,)),
        ("principal_axes/moments", lambda J: inertia.principal_axes(J)[0], (J0,)),
        ("principal_axes/axes", axes_invariant, (J0,)),
        ("ellipsoid_semi_axes", lambda J: inertia.ellipsoid_semi_axes(J)[0], (J0,)),
        # Symmetric perturbations keep J physical, as these functions require.
        ("check_inertia", lambda X: inertia.check_inertia(J0 + sym(X)), (X0,)),
        ("to_log_cholesky", lambda X: inertia.to_log_cholesky(J0 + sym(X)), (X0,)),
        ("from_log_cholesky", inertia.from_log_cholesky, (rng.uniform(-1.0, 1.0, 6),)),
        ("kinetic_energy", inertia.kinetic_energy, (J0, omega)),
        ("angular_momentum", inertia.angular_momentum, (J0, omega)),
        ("moment_about", inertia.moment_about, (J0, rng.normal(size=3))),
    ]


def test_grads_vs_finite_differences(rng):
    cases = _grad_cases(rng)
    args = {name: a for name, _, a in cases}

    # All cases in one jitted program (one compilation instead of fourteen); check_grads draws
    # a random tangent for every argument, so an error in any case fails the check (call
    # check_grads on that case alone to localise it).
    @jax.jit
    def all_cases(args):
        return {name: f(*args[name]) for name, f, _ in cases}

    check_grads(all_cases, (args,), 1, atol=FD_TOL, rtol=FD_TOL)


def test_second_order_grads_log_cholesky(rng):
    # Second derivatives of the parametrisation used in identification (Hessians, Gauss-Newton).
    theta = rng.uniform(-1.0, 1.0, 6)
    check_grads(
        jax.jit(inertia.from_log_cholesky), (theta,), 2, modes=("rev",), atol=FD_TOL, rtol=FD_TOL
    )


def test_grads_closed_forms(rng):
    J = random_physical(rng)
    omega = rng.normal(size=3)
    axis = rng.normal(size=3)
    # Closed forms: ∂T/∂J = ½ ω ωᵀ, ∂T/∂ω = J ω (J symmetric), ∂(nᵀJn)/∂J = n nᵀ.
    gJ, gw = jax.grad(inertia.kinetic_energy, argnums=(0, 1))(J, omega)
    np.testing.assert_allclose(gJ, 0.5 * np.outer(omega, omega), rtol=1e-14)
    np.testing.assert_allclose(gw, J @ omega, rtol=1e-13)
    n = axis / np.linalg.norm(axis)
    np.testing.assert_allclose(jax.grad(inertia.moment_about)(J, axis), np.outer(n, n), atol=1e-14)
    # At degenerate moments (A = B) the moments' gradient stays finite: d(ΣA)/dJ = I exactly.
    J_sym = np.diag([1.0, 1.0, 2.0])
    g = jax.grad(lambda J: jnp.sum(inertia.principal_axes(J)[0]))(J_sym)
    np.testing.assert_allclose(g, np.eye(3), atol=1e-14)


def test_grad_through_log_cholesky_energy(rng):
    theta = rng.uniform(-1.0, 1.0, 6)
    omega = rng.normal(size=3)

    @jax.jit
    def energy(th):
        return inertia.kinetic_energy(inertia.from_log_cholesky(th), omega)

    g = jax.grad(energy)(theta)
    h = 1e-6  # central difference: error O(h²·T''') ≪ 1e-7
    fd = np.array([(energy(theta + h * e) - energy(theta - h * e)) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-7)


# ---------------------------------------------------------------- shape errors


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: inertia.planar(np.ones(3)), "`J`"),
        (lambda: inertia.from_planar(np.ones((3, 4))), "`Jp`"),
        (lambda: inertia.principal_axes(np.ones((2, 2))), "`J`"),
        (lambda: inertia.from_principal(np.ones(2)), "`moments`"),
        (lambda: inertia.from_principal(np.ones(3), np.eye(2)), "`axes`"),
        (lambda: inertia.from_point_masses(np.ones(3), np.ones((4, 3))), "`masses`"),
        (lambda: inertia.from_point_masses(np.ones(4), np.ones((4, 2))), "`positions`"),
        (lambda: inertia.from_point_masses(np.ones(4), np.ones((4, 3)), np.ones(2)), "`about`"),
        (lambda: inertia.moment_about(np.eye(3), np.ones(4)), "`axis`"),
        (lambda: inertia.kinetic_energy(np.eye(3), np.ones(2)), "`omega`"),
        (lambda: inertia.angular_momentum(np.ones((3, 2)), np.ones(3)), "`J`"),
        (lambda: inertia.is_physical(np.ones(9)), "`J`"),
        (lambda: inertia.check_inertia(np.ones(3), name="J_body"), "`J_body`"),
        (lambda: inertia.to_log_cholesky(np.ones((3,))), "`J`"),
        (lambda: inertia.from_log_cholesky(np.ones(5)), "`theta`"),
    ],
)
def test_shape_errors_name_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()
