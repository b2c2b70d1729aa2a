"""The simulator against the analytic references of `rbdyn_jax.analytic`.

`analytic` is closed form / quadrature (proved against scipy's solve_ivp and special
functions in test_analytic.py); here the diffrax solves of the library's own models must
reproduce it.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb
from rbdyn_jax import analytic

RTOL = ATOL = 1e-10


# ------------------------------------------------------------------------------------------
# Torque-free body vs Jacobi elliptic functions, ≥ 20 periods (docs/physics.md#torque-free-motion)
# ------------------------------------------------------------------------------------------

# (principal moments in any order, ω0 in those principal axes): both sides of the
# separatrix (circulation about the largest and about the smallest moment), every ordering
# of the moments, mixed signs.
TORQUE_FREE_CASES = [
    ([1.0, 2.0, 3.0], [0.3, 0.4, 1.2]),  # about the largest axis
    ([1.0, 2.0, 3.0], [1.1, 0.5, -0.2]),  # about the smallest axis
    ([3.0, 1.0, 2.0], [-0.7, 0.2, 0.9]),
    ([2.0, 3.0, 1.5], [0.4, -0.8, 0.6]),
    ([1.2, 2.5, 2.0], [0.9, 0.3, -0.5]),
]
N_PERIODS = 20


@pytest.mark.parametrize("moments, omega0", TORQUE_FREE_CASES)
def test_torque_free_matches_elliptic_solution(moments, omega0):
    moments = np.asarray(moments)
    omega0 = np.asarray(omega0)
    # General J with products of inertia: principal axes = columns of a random rotation.
    C = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    J = rb.inertia.from_principal(moments, C)
    period = float(analytic.torque_free_elliptic_period(moments, omega0))
    assert np.isfinite(period)
    ts = jnp.linspace(0.0, N_PERIODS * period, 801)
    model = rb.RigidBody(J)
    y0 = rb.State(omega=jnp.asarray(C @ omega0), quat=jnp.array([1.0, 0.0, 0.0, 0.0]))
    traj = rb.simulate(model, y0, ts, rtol=RTOL, atol=ATOL)
    w_principal = np.asarray(traj.ys.omega) @ C  # Cᵀ ω at each time
    w_ref = np.asarray(analytic.torque_free_elliptic(moments, omega0, ts))
    scale = np.linalg.norm(omega0)
    # The local errors (≤ rtol per step, 2000–3500 steps) accumulate mostly as a phase
    # drift: measured ≤ 2.7e-9 relative over 20 periods at rtol = 1e-10. The bound, 3e-8,
    # keeps a 10× margin and is far below the O(1e-2) departure a wrong term or a 1 %
    # inertia error gives (test_reference_is_not_trivially_matched).
    err = np.max(np.abs(w_principal - w_ref)) / scale
    assert err < 3e-8, err
    T = np.asarray(rb.invariants.kinetic_energy(model, traj))
    L = np.asarray(rb.invariants.angular_momentum_inertial(model, traj))
    # First integrals: T and the inertial L (drift ~ steps × rtol at worst; measured ≤ 1.1e-9).
    assert np.max(np.abs(T - T[0])) / T[0] < 1e-8
    assert np.max(np.linalg.norm(L - L[:1], axis=-1)) / np.linalg.norm(L[0]) < 1e-8


def test_torque_free_symmetric_attitude():
    """Axisymmetric body: ω and the attitude vs the closed form
    (docs/physics.md#torque-free-motion)."""
    A, Cm = 2.0, 3.5
    omega0 = jnp.array([0.3, -0.4, 1.5])
    q0 = jnp.asarray(Rotation.from_rotvec([0.2, 0.5, -0.1]).as_quat(scalar_first=True))
    ts = jnp.linspace(0.0, 60.0, 601)
    traj = rb.simulate(
        rb.RigidBody(jnp.diag(jnp.array([A, A, Cm]))),
        rb.State(omega0, q0),
        ts,
        rtol=RTOL,
        atol=ATOL,
    )
    w_ref, q_ref = analytic.torque_free_symmetric(A, Cm, omega0, ts, q0)
    np.testing.assert_allclose(traj.ys.omega, w_ref, atol=1e-7)  # 60 s, ~1000 steps at 1e-10
    sign = np.sign(np.sum(np.asarray(traj.ys.quat) * np.asarray(q_ref), -1, keepdims=True))
    np.testing.assert_allclose(traj.ys.quat, sign * np.asarray(q_ref), atol=1e-7)


# ------------------------------------------------------------------------------------------
# Lagrange top under k(τ, ψ) = ε K(τ) sin ψ vs the first approximation
# (docs/physics.md#first-approximation)
# ------------------------------------------------------------------------------------------

# The assumptions of Zinkevich & Kozachenko (2008), eq. (2): √(p² + q²) ≪ r (p, q start at 0 and
# stay O(ε)), C r² = 1.5 ≫ k, K(τ) > 0 on [0, 1] so ψ moves from 1.0 to ≈ 1.8 rad, away from the
# fixed points of sin ψ.
TOP = dict(A=1.0, C=1.5, r0=1.0, psi0=1.0, theta0=0.8)
K_COEFFS = (1.0, 0.8, -0.5)  # K(τ) = 1 + 0.8 τ − 0.5 τ²


def K_of_tau(s):
    return K_COEFFS[0] + K_COEFFS[1] * s + K_COEFFS[2] * s**2


def top_errors(eps, form):
    M3 = eps**2  # constant perturbing moment M3 = ε² M3*, M3* = 1 (their eq. (3))
    torque = rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array(K_COEFFS), eps)) + rb.BodyTorque(
        jnp.array([0.0, 0.0, M3])
    )
    J = jnp.diag(jnp.array([TOP["A"], TOP["A"], TOP["C"]]))
    angles0 = jnp.array([TOP["psi0"], TOP["theta0"], 0.3])
    omega0 = jnp.array([0.0, 0.0, TOP["r0"]])
    ts = jnp.linspace(0.0, 1.0 / eps, 1001)
    if form == "euler":
        traj = rb.simulate(
            rb.EulerAngleRigidBody(J, torque),
            rb.EulerState(omega0, angles0),
            ts,
            rtol=RTOL,
            atol=ATOL,
        )
        angles = np.asarray(traj.ys.angles)
    else:
        traj = rb.simulate(
            rb.RigidBody(J, torque),
            rb.State(omega0, rb.rotation.euler_to_quat(angles0, "ZXZ")),
            ts,
            rtol=RTOL,
            atol=ATOL,
        )
        angles = np.unwrap(np.asarray(rb.rotation.quat_to_euler(traj.ys.quat, "ZXZ")), axis=0)
    psi, theta, r = analytic.lagrange_top_first_approximation(ts, **TOP, eps=eps, K=K_of_tau, M3=M3)
    np.testing.assert_allclose(traj.ys.omega[:, 2], r, atol=1e-9)  # C r' = M3 exactly
    return (
        float(np.max(np.abs(angles[:, 0] - np.asarray(psi)))),
        float(np.max(np.abs(angles[:, 1] - np.asarray(theta)))),
    )


@pytest.mark.parametrize("form", ["euler", "quaternion"])
def test_lagrange_top_first_approximation_error_is_order_eps(form):
    """Over t ∈ [0, 1/ε] the averaged solution is O(ε) accurate
    (docs/physics.md#first-approximation): halving
    ε halves the error (test_analytic measures ratios 1.98–2.06 against solve_ivp); the
    solver error (~1e-8) is far below the O(ε) ≈ 1e-2 being measured."""
    psi02, theta02 = top_errors(0.02, form)
    psi01, theta01 = top_errors(0.01, form)
    assert 1.5 < psi02 / psi01 < 3.0, (psi02, psi01)
    assert 1.5 < theta02 / theta01 < 3.0, (theta02, theta01)
    assert psi01 < 0.01 and theta01 < 0.01


# ------------------------------------------------------------------------------------------
# Integrable gravity-gradient case, nutation half period vs the quadrature
# (docs/physics.md#nutation-quadrature)
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "omega0, gamma0",
    [
        ([0.3, -0.2, 1.0], [0.0, 0.6, 0.8]),
        ([0.5, 0.4, 0.3], [0.48, 0.0, 0.8774964387392122]),
    ],
)
def test_gg_nutation_half_period_matches_quadrature(omega0, gamma0):
    A, Cm, eps = 1.0, 1.6, 1.0
    omega0, gamma0 = np.asarray(omega0), np.asarray(gamma0)
    gamma0 = gamma0 / np.linalg.norm(gamma0)
    half = analytic.gg_nutation_half_period(A, Cm, eps, omega0, gamma0)
    ts = jnp.linspace(0.0, 8.0 * half, 4001)
    model = rb.PoissonRigidBody(jnp.diag(jnp.array([A, A, Cm])), rb.GravityGradient(eps))
    traj = rb.simulate(
        model, rb.PoissonState(jnp.asarray(omega0), jnp.asarray(gamma0)), ts, rtol=RTOL, atol=ATOL
    )
    # Turning points of γ'' are the zeros of dγ''/dt = q γ − p γ' (Poisson,
    # docs/physics.md#poisson-equations),
    # located by linear interpolation between output times (spacing h = 8 half / 4000: the
    # interpolation error is O(h²) ≈ 1e-6 relative; the solver's ~1e-9 is negligible).
    w, g = np.asarray(traj.ys.omega), np.asarray(traj.ys.gamma)
    rate = w[:, 1] * g[:, 0] - w[:, 0] * g[:, 1]
    t = np.asarray(ts)
    i = np.nonzero(np.sign(rate[:-1]) * np.sign(rate[1:]) < 0)[0]
    roots = t[i] - rate[i] * (t[i + 1] - t[i]) / (rate[i + 1] - rate[i])
    assert len(roots) >= 6
    np.testing.assert_allclose(np.diff(roots), half, rtol=1e-5)
    # and the four integrals of the case hold to the solver tolerance (≈100 × rtol)
    for x in rb.invariants.gg_integrable_integrals(model, traj):
        assert np.max(np.abs(np.asarray(x) - np.asarray(x)[0])) < 1e-8


def test_reference_is_not_trivially_matched():
    """The references are sharp enough to catch a wrong model: a 1 % error in one moment
    gives an O(1e-2) departure from the elliptic solution within a few periods."""
    moments, omega0 = np.array([1.0, 2.0, 3.0]), np.array([0.3, 0.4, 1.2])
    ts = jnp.linspace(0.0, 5 * float(analytic.torque_free_elliptic_period(moments, omega0)), 201)
    traj = rb.simulate(
        rb.RigidBody(jnp.diag(jnp.asarray(moments * [1.0, 1.01, 1.0]))),
        rb.State(jnp.asarray(omega0), jnp.array([1.0, 0, 0, 0])),
        ts,
        rtol=RTOL,
        atol=ATOL,
    )
    err = np.max(
        np.abs(
            np.asarray(traj.ys.omega)
            - np.asarray(analytic.torque_free_elliptic(moments, omega0, ts))
        )
    )
    assert err > 1e-3
