"""rbdyn_jax.analytic against independent references.

References, none of which shares code with the module:

- `scipy.special.ellipj / ellipk / ellipkinc` (Cephes) for the JAX special functions;
- `scipy.integrate.solve_ivp` (DOP853, rtol = atol = 1e-12) of the equations of motion written
  out below in NumPy: Euler's equations with quaternion kinematics
  (docs/physics.md#torque-free-motion), the Lagrange top with ZXZ kinematics
  (docs/physics.md#equations-of-motion), the gravity-gradient equations with Poisson
  kinematics (docs/physics.md#torque-and-integrals);
- first integrals (T, L², the integrals C1, C2 of docs/physics.md#the-integrable-case) and
  exact identities.

Tolerances. Solver-vs-analytic comparisons over ≥ 20 periods see the solver's global error,
which grows linearly in time: measured ≤ 1e-9 |ω0| for the elliptic case (≈ 5e-11 per period),
so 1e-8. Identities and special functions are float64 rounding: 1e-13 (a few ulps of O(1) values
after O(10) operations). The asymptotic references of the restoring moment
(docs/physics.md#averaging) are tested by their convergence order in ε, the property that
defines them.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp
from helpers import assert_quat_equal
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from rbdyn_jax import analytic as an

IVP = dict(method="DOP853", rtol=1e-12, atol=1e-12)
# Identities and special functions: float64 rounding of O(1) values.
TIGHT = 1e-13
# Solver vs closed form over ≥ 20 periods (solver global error, measured ≤ 1e-9).
SOLVER = 1e-8
# One number of sample times for the elliptic tests: one compilation serves them all.
N = 1001


# ---------------------------------------------------------------------------------------
# reference equations in NumPy (independent of the package)
# ---------------------------------------------------------------------------------------


def euler_rhs(t, w, I1, I2, I3):
    """Euler's equations A p' = (B − C) q r, ... (docs/physics.md#eulers-equations), body
    principal axes."""
    p, q, r = w
    return [(I2 - I3) * q * r / I1, (I3 - I1) * r * p / I2, (I1 - I2) * p * q / I3]


def euler_quat_rhs(t, y, I1, I2, I3):
    """Euler's equations and q' = ½ q ⊗ (0, ω), q = [w, x, y, z]."""
    p, q, r, w, x, yy, z = y
    return euler_rhs(t, (p, q, r), I1, I2, I3) + [
        0.5 * (-x * p - yy * q - z * r),
        0.5 * (w * p + yy * r - z * q),
        0.5 * (w * q + z * p - x * r),
        0.5 * (w * r + x * q - yy * p),
    ]


def solve_euler(I, w0, ts):
    """Euler's equations from t = 0 to every time in `ts` (both signs allowed)."""
    ts = np.asarray(ts)
    out = np.empty((ts.size, 3))
    for sel in (ts >= 0, ts < 0):
        if sel.any():
            t_sel = ts[sel]
            order = np.argsort(np.abs(t_sel))
            end = t_sel[order[-1]]
            sol = solve_ivp(euler_rhs, (0.0, end), w0, t_eval=t_sel[order], args=tuple(I), **IVP)
            assert sol.success
            out[np.flatnonzero(sel)[order]] = sol.y.T
    return out


def energy_momentum(I, w):
    return np.sum(I * w * w, -1), np.sum((I * w) ** 2, -1)


# ---------------------------------------------------------------------------------------
# special functions
# ---------------------------------------------------------------------------------------


def test_ellipj_matches_scipy(rng):
    u = rng.uniform(-20, 20, 4000)
    m = np.concatenate(
        [
            [0.0] * 100,
            10 ** rng.uniform(-16, -1, 400),
            rng.uniform(0, 1, 3000),
            1 - 10 ** rng.uniform(-9, -1, 500),
        ]
    )
    got = np.asarray(jax.jit(an.ellipj)(u, m))
    ref = np.stack(sp.ellipj(u, m)[:3])
    np.testing.assert_allclose(got, ref, atol=TIGHT, rtol=0)


def test_ellipj_near_and_at_m_equal_one(rng):
    # Cephes switches to a first-order expansion in 1 − m above 1 − 1e-9 (error
    # O((1 − m)² e^{2|u|})), good for |u| ≤ 5; our Landen branch is used up to m < 1.
    u = rng.uniform(-5, 5, 500)
    m = 1 - 10 ** rng.uniform(-16, -9, 500)
    np.testing.assert_allclose(
        np.asarray(an.ellipj(u, m)), np.stack(sp.ellipj(u, m)[:3]), atol=1e-12
    )
    sn, cn, dn = an.ellipj(u, 1.0)
    sech = 1 / np.cosh(u)
    np.testing.assert_allclose(np.asarray([sn, cn, dn]), [np.tanh(u), sech, sech], atol=TIGHT)


def test_ellipj_identities_and_derivative(rng):
    """sn² + cn² = 1, dn² + m sn² = 1, d sn/du = cn dn: everywhere, including m → 1."""
    u = rng.uniform(-50, 50, 2000)
    m = np.concatenate([rng.uniform(0, 1, 1000), 1 - 10 ** rng.uniform(-16, -1, 1000)])
    sn, cn, dn = an.ellipj(u, m)
    np.testing.assert_allclose(sn**2 + cn**2, 1.0, atol=TIGHT)
    np.testing.assert_allclose(dn**2 + m * sn**2, 1.0, atol=TIGHT)
    f = lambda uu: an.ellipj(uu, m)[0]  # noqa: E731
    _, dsn = jax.jvp(f, (jnp.asarray(u),), (jnp.ones_like(u),))
    # jvp through the Landen recursion: rounding of φ_N = 2^N a u grows like |u|.
    np.testing.assert_allclose(dsn, cn * dn, atol=1e-11)


def test_ellipk_and_ellipkinc_match_scipy(rng):
    m = np.concatenate([rng.uniform(0, 1, 1000), 1 - 10 ** rng.uniform(-16, -1, 200), [0.0]])
    np.testing.assert_allclose(an.ellipk(m), sp.ellipk(m), rtol=TIGHT)
    phi = rng.uniform(-10, 10, m.size)
    np.testing.assert_allclose(an.ellipkinc(phi, m), sp.ellipkinc(phi, m), rtol=TIGHT, atol=TIGHT)
    # F is odd and quasi-periodic: F(φ + π) = F(φ) + 2K.
    np.testing.assert_allclose(
        an.ellipkinc(phi + np.pi, m), an.ellipkinc(phi, m) + 2 * an.ellipk(m), rtol=TIGHT
    )


# ---------------------------------------------------------------------------------------
# torque-free axisymmetric body
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("A, C", [(1.0, 2.0), (2.0, 1.0), (1.5, 1.5)])
def test_symmetric_matches_solve_ivp(rng, A, C):
    w0 = rng.normal(size=3)
    q0 = Rotation.random(random_state=rng).as_quat(scalar_first=True)
    lam = (C - A) * w0[2] / A
    T = 20 * 2 * np.pi / abs(lam) if lam != 0 else 50.0
    ts = np.linspace(0, T, N)
    sol = solve_ivp(euler_quat_rhs, (0, T), np.r_[w0, q0], t_eval=ts, args=(A, A, C), **IVP)
    omega, quat = an.torque_free_symmetric(A, C, w0, ts, q0)
    np.testing.assert_allclose(omega, sol.y[:3].T, atol=SOLVER * np.abs(w0).max())
    assert_quat_equal(quat, sol.y[3:].T, atol=SOLVER)


def test_symmetric_identities(rng):
    """q' = ½ q ⊗ (0, ω) exactly (jvp in t), |q| = 1, and L_inertial = R J ω constant."""
    A, C = 1.3, 0.7
    w0 = rng.normal(size=3)
    q0 = Rotation.random(random_state=rng).as_quat(scalar_first=True)
    ts = jnp.linspace(-30.0, 30.0, 301)
    f = lambda t: an.torque_free_symmetric(A, C, w0, t, q0)  # noqa: E731
    (omega, quat), (_, dquat) = jax.jvp(f, (ts,), (jnp.ones_like(ts),))
    w, x, y, z = np.moveaxis(np.asarray(quat), -1, 0)
    p, q, r = np.moveaxis(np.asarray(omega), -1, 0)
    expected = 0.5 * np.stack(
        [
            -x * p - y * q - z * r,
            w * p + y * r - z * q,
            w * q + z * p - x * r,
            w * r + x * q - y * p,
        ],
        -1,
    )
    np.testing.assert_allclose(dquat, expected, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=TIGHT)
    R = Rotation.from_quat(np.asarray(quat), scalar_first=True).as_matrix()
    L = np.einsum("nij,nj->ni", R, np.array([A, A, C]) * np.asarray(omega))
    np.testing.assert_allclose(L, np.broadcast_to(L[150], L.shape), atol=1e-12)
    # default attitude: identity at t = 0
    _, quat_default = an.torque_free_symmetric(A, C, w0, np.linspace(0.0, 1.0, N))
    np.testing.assert_allclose(quat_default[0], [1, 0, 0, 0], atol=TIGHT)


def test_symmetric_batch_and_vmap(rng):
    A = rng.uniform(1, 2, (2, 3))
    C = rng.uniform(1, 2, (2, 3))
    w0 = rng.normal(size=(2, 3, 3))
    ts = jnp.linspace(0, 5, N)
    omega, quat = an.torque_free_symmetric(A, C, w0, ts)
    assert omega.shape == (2, 3, N, 3) and quat.shape == (2, 3, N, 4)
    o11, q11 = an.torque_free_symmetric(A[1, 1], C[1, 1], w0[1, 1], ts)
    np.testing.assert_allclose(omega[1, 1], o11, atol=TIGHT)
    np.testing.assert_allclose(quat[1, 1], q11, atol=TIGHT)
    ov, _ = jax.vmap(an.torque_free_symmetric, in_axes=(0, 0, 0, None))(A[0], C[0], w0[0], ts)
    np.testing.assert_allclose(ov, omega[0], atol=TIGHT)


# ---------------------------------------------------------------------------------------
# torque-free triaxial body (Jacobi elliptic functions)
# ---------------------------------------------------------------------------------------


def elliptic_cases(rng):
    """Every ordering of the moments, each on both sides of the separatrix, random signs."""
    import itertools

    moments, omegas = [], []
    for perm in itertools.permutations(range(3)):
        base = np.array([1.0, 2.0, 3.0]) * rng.uniform(0.5, 2.0)
        for w_sorted in ([0.3, 0.5, 1.0], [1.0, 0.5, 0.3]):  # L² > 2TB, L² < 2TB
            w = np.array(w_sorted) * rng.choice([-1.0, 1.0], 3) * rng.uniform(0.5, 2.0)
            I = np.empty(3)
            om = np.empty(3)
            I[list(perm)] = base
            om[list(perm)] = w
            moments.append(I)
            omegas.append(om)
    return np.array(moments), np.array(omegas)


def side(I, w):
    T2, L2 = energy_momentum(I, w)
    return np.sign(L2 - T2 * np.sort(I)[1])


def test_elliptic_matches_solve_ivp_all_orderings(rng):
    """Every ordering of the moments, both sides of the separatrix, random signs of ω0, over
    20 periods; evaluated as a benchmark would, `jit(vmap(...))` over the initial conditions,
    which must equal the one-by-one evaluation."""
    moments, omegas = elliptic_cases(rng)
    sides = np.array([side(I, w) for I, w in zip(moments, omegas)])
    assert (sides > 0).sum() == 6 and (sides < 0).sum() == 6
    periods = np.asarray(jax.jit(jax.vmap(an.torque_free_elliptic_period))(moments, omegas))
    np.testing.assert_allclose(periods, an.torque_free_elliptic_period(moments, omegas), rtol=TIGHT)
    ts = np.linspace(0.0, 1.0, N)[None, :] * 20 * periods[:, None]
    got = np.asarray(jax.jit(jax.vmap(an.torque_free_elliptic))(moments, omegas, ts))
    for k, (I, w0, t, g) in enumerate(zip(moments, omegas, ts, got)):
        ref = solve_euler(I, w0, t)
        np.testing.assert_allclose(g, ref, atol=SOLVER * np.abs(w0).max(), rtol=0)
        # exact first integrals along the closed form
        T2, L2 = energy_momentum(I, g)
        T20, L20 = energy_momentum(I, w0)
        np.testing.assert_allclose(T2, T20, rtol=1e-12)
        np.testing.assert_allclose(L2, L20, rtol=1e-12)
        if k % 4 == 0:  # vmap equals the loop
            np.testing.assert_allclose(g, an.torque_free_elliptic(I, w0, t), atol=TIGHT)


def test_elliptic_negative_times_and_near_separatrix():
    I = np.array([2.0, 1.0, 3.0])  # odd ordering: time reversed in the sorted frame
    w0 = np.array([0.3, -1.0, 0.5])
    per = float(an.torque_free_elliptic_period(I, w0))
    ts = np.linspace(-10 * per, 5 * per, N)
    np.testing.assert_allclose(
        an.torque_free_elliptic(I, w0, ts), solve_euler(I, w0, ts), atol=SOLVER
    )
    # 1 − m ≈ 1e-4 on both sides: close to the separatrix (K ≈ 6), computed without
    # cancellation from d2 = L² − 2TB.
    I = np.array([3.0, 5.0, 6.0])
    for w3 in (0.7 * (1 + 1e-4), 0.7 * (1 - 1e-4)):
        w0 = np.array([0.7, 0.2, -w3])
        per = float(an.torque_free_elliptic_period(I, w0))
        ts = np.linspace(0, 5 * per, N)
        np.testing.assert_allclose(
            an.torque_free_elliptic(I, w0, ts), solve_euler(I, w0, ts), atol=SOLVER
        )


@pytest.mark.parametrize("signs", [(1, 1, 1), (-1, 1, 1), (1, -1, -1), (-1, -1, 1)])
def test_elliptic_exactly_on_the_separatrix(signs):
    """I = (3, 5, 6), ω1 = ±ω3: L² = 2TB exactly in float64; the sech/tanh solution."""
    I = np.array([3.0, 5.0, 6.0])
    w0 = np.array([0.7, 0.2, 0.7]) * np.array(signs)
    # d2 = L² − 2TB written without cancellation (sorted axes): exactly zero here
    assert I[2] * (I[2] - I[1]) * w0[2] ** 2 - I[0] * (I[1] - I[0]) * w0[0] ** 2 == 0
    ts = np.linspace(-30, 30, N)
    np.testing.assert_allclose(
        an.torque_free_elliptic(I, w0, ts), solve_euler(I, w0, ts), atol=1e-10
    )
    # permuted axes (odd and even permutations) give the permuted solution
    for perm in ([1, 2, 0], [2, 1, 0]):
        got = an.torque_free_elliptic(I[perm], w0[perm], ts)
        np.testing.assert_allclose(got, solve_euler(I[perm], w0[perm], ts), atol=1e-10)
    assert float(an.torque_free_elliptic_period(I, w0)) == math.inf


@pytest.mark.parametrize("I", [[1.0, 1.0, 2.0], [2.0, 1.0, 2.0], [2.0, 2.0, 1.0], [1.0, 3.0, 3.0]])
def test_elliptic_delegates_to_symmetric(rng, I):
    I = np.array(I)
    w0 = rng.normal(size=3)
    per = float(an.torque_free_elliptic_period(I, w0))
    unique = int(np.flatnonzero([np.sum(I == x) == 1 for x in I])[0])
    eq = I[(unique + 1) % 3]
    assert per == pytest.approx(2 * np.pi * eq / abs((I[unique] - eq) * w0[unique]), rel=1e-14)
    ts = np.linspace(0, 20 * per, N)
    np.testing.assert_allclose(
        an.torque_free_elliptic(I, w0, ts), solve_euler(I, w0, ts), atol=SOLVER
    )


def test_elliptic_degenerate_cases():
    ts = np.linspace(-5, 5, N)
    I = np.array([1.0, 2.0, 3.0])
    for k in range(3):  # spin about each principal axis, including the unstable one
        w0 = 1.3 * np.eye(3)[k]
        np.testing.assert_array_equal(an.torque_free_elliptic(I, w0, ts), np.tile(w0, (N, 1)))
    per = np.asarray(an.torque_free_elliptic_period(np.tile(I, (3, 1)), 1.3 * np.eye(3)))
    # spins about the extreme axes: the small-oscillation period of nearby polhodes
    small = [2 * np.pi / (1.3 * np.sqrt((2 - 1) * (3 - 1) / (2 * 3))), math.inf]
    small.append(2 * np.pi / (1.3 * np.sqrt((3 - 1) * (3 - 2) / (1 * 2))))
    np.testing.assert_allclose(per, small, rtol=1e-14)
    w0 = np.array([0.3, -0.2, 0.9])
    np.testing.assert_array_equal(an.torque_free_elliptic(np.ones(3), w0, ts), np.tile(w0, (N, 1)))
    assert float(an.torque_free_elliptic_period(np.ones(3), w0)) == math.inf
    np.testing.assert_array_equal(an.torque_free_elliptic(I, np.zeros(3), ts), 0.0)
    assert float(an.torque_free_elliptic_period(I, np.zeros(3))) == math.inf


def test_elliptic_period_matches_measured_period(rng):
    """Successive upward zero crossings of the intermediate-axis rate in solve_ivp."""

    def crossing(t, w, *args):
        return w[1]

    crossing.direction = 1.0
    moments, omegas = elliptic_cases(rng)
    periods = np.asarray(an.torque_free_elliptic_period(moments, omegas))
    for I, w0, per in list(zip(moments, omegas, periods))[::2]:
        order = np.argsort(I)  # the intermediate axis is index 1 of the sorted axes
        sol = solve_ivp(
            euler_rhs, (0, 5.5 * per), w0[order], events=crossing, args=tuple(I[order]), **IVP
        )
        measured = np.diff(sol.t_events[0])
        assert measured.size >= 4
        np.testing.assert_allclose(measured, per, rtol=1e-10)


def test_elliptic_batch_shapes(rng):
    """Leading *batch axes, broadcast between the arguments (the machinery, shared with
    `torque_free_elliptic`, is `jnp.vectorize` after an explicit broadcast)."""
    moments, omegas = elliptic_cases(rng)
    moments, omegas = moments.reshape(3, 4, 3), omegas.reshape(3, 4, 3)
    per = an.torque_free_elliptic_period(moments[:, :1], omegas)  # moments broadcast on axis 1
    assert per.shape == (3, 4)
    np.testing.assert_allclose(
        per[2, 3], an.torque_free_elliptic_period(moments[2, 0], omegas[2, 3]), rtol=TIGHT
    )


def test_torque_free_bad_input():
    with pytest.raises(ValueError, match="`moments`"):
        an.torque_free_elliptic(np.ones(2), np.ones(3), np.linspace(0, 1, 3))
    with pytest.raises(ValueError, match="`omega0`"):
        an.torque_free_symmetric(1.0, 2.0, np.ones(4), np.linspace(0, 1, 3))
    with pytest.raises(ValueError, match="`ts`"):
        an.torque_free_symmetric(1.0, 2.0, np.ones(3), 1.0)
    with pytest.raises(eqx.EquinoxRuntimeError, match="`moments` must be positive"):
        an.torque_free_elliptic(np.array([1.0, -2.0, 3.0]), np.ones(3), np.linspace(0, 1, 3))


# ---------------------------------------------------------------------------------------
# Lagrange top under k(τ, ψ) = ε K(τ) sin ψ (docs/physics.md#restoring-moment)
# ---------------------------------------------------------------------------------------

# The assumptions of Zinkevich & Kozachenko (2008), eq. (2): √(p² + q²) ≪ r (p, q = O(ε)),
# C r² = 1.5 ≫ k ≤ 1.3 ε, and n0/r0 = (C − A)/A = 0.5 ≤ 1. K varies with τ (non-stationary)
# and stays positive on [0, 1], so ψ moves from 1.0 to ≈ 1.8 rad over t = 1/ε, away from the
# fixed points 0 and π of sin ψ.
TOP = dict(A=1.0, C=1.5, r0=1.0, psi0=1.0, theta0=0.8)
PHI0 = 0.3


def K_of_tau(s):
    return 1.0 + 0.8 * s - 0.5 * s**2


def lagrange_rhs(t, y, eps, M3):
    """docs/physics.md#equations-of-motion with the inverse ZXZ kinematics of
    docs/physics.md#euler-angle-rates (M1 = M2 = 0)."""
    A, C = TOP["A"], TOP["C"]
    p, q, r, psi, th, phi = y
    k = eps * K_of_tau(eps * t) * np.sin(psi)
    sf, cf, st = np.sin(phi), np.cos(phi), np.sin(th)
    u = p * sf + q * cf
    return [
        (k * st * cf - (C - A) * q * r) / A,
        (-k * st * sf - (A - C) * p * r) / A,
        M3 / C,
        u / st,
        p * cf - q * sf,
        r - u * np.cos(th) / st,
    ]


def initial_rates(eps, start):
    """p0 = q0 = 0 ("rest": the axis starts without precession, full nutation), or the
    steady-precession rates p = ψ' sinθ sinφ, q = ψ' sinθ cosφ with ψ' = k0 / (C r0)."""
    if start == "rest":
        return 0.0, 0.0
    rate = eps * K_of_tau(0.0) * np.sin(TOP["psi0"]) / (TOP["C"] * TOP["r0"])
    st = np.sin(TOP["theta0"])
    return rate * st * np.sin(PHI0), rate * st * np.cos(PHI0)


def top_errors(eps, start, M3_star):
    M3 = M3_star * eps**2  # Zinkevich & Kozachenko (2008), eq. (3): M_i = ε² M_i*
    p0, q0 = initial_rates(eps, start)
    ts = np.linspace(0, 1 / eps, 2001)
    y0 = [p0, q0, TOP["r0"], TOP["psi0"], TOP["theta0"], PHI0]
    sol = solve_ivp(lagrange_rhs, (0, ts[-1]), y0, t_eval=ts, args=(eps, M3), **IVP)
    p1, t1, r1 = an.lagrange_top_first_approximation(ts, **TOP, eps=eps, K=K_of_tau, M3=M3)
    p2, t2, r2 = an.lagrange_top_second_approximation(
        ts, **TOP, eps=eps, K=K_of_tau, M3=M3, phi0=PHI0, p0=p0, q0=q0
    )
    np.testing.assert_allclose(r1, sol.y[2], atol=1e-13)
    np.testing.assert_allclose(r2, sol.y[2], atol=1e-13)
    err = lambda a, b: float(np.max(np.abs(np.asarray(a) - b)))  # noqa: E731
    return {
        "psi1": err(p1, sol.y[3]),
        "theta1": err(t1, sol.y[4]),
        "psi2": err(p2, sol.y[3]),
        "theta2": err(t2, sol.y[4]),
    }


@pytest.mark.parametrize("start", ["rest", "steady"])
@pytest.mark.parametrize("M3_star", [0.0, 1.0])
def test_lagrange_top_convergence_orders(start, M3_star):
    """Over t ∈ [0, 1/ε]: first approximation O(ε), second O(ε²) (measured ratios on
    halving ε: 1.98–2.06 and 4.02–4.08; errors ≤ 0.7 ε and ≤ 0.8 ε²)."""
    e02 = top_errors(0.02, start, M3_star)
    e01 = top_errors(0.01, start, M3_star)
    for key in ("psi1", "theta1"):
        assert 1.5 < e02[key] / e01[key] < 3.0, (key, e02[key], e01[key])
        assert e01[key] < 1.0 * 0.01
    for key in ("psi2", "theta2"):
        assert 3.0 < e02[key] / e01[key] < 5.0, (key, e02[key], e01[key])
        assert e01[key] < 1.0 * 0.01**2


def test_lagrange_first_approximation_closed_form():
    """ψ' = k / (C r0) at t = 0 (heavy-top sign: positive for k, r0 > 0), and F1 by the
    Gauss–Legendre rule vs scipy quad for a non-polynomial K."""
    eps = 0.01
    f = lambda t: an.lagrange_top_first_approximation(t, **TOP, eps=eps, K=K_of_tau)[0]  # noqa: E731
    _, dpsi = jax.jvp(f, (jnp.zeros(1),), (jnp.ones(1),))
    expected = eps * K_of_tau(0.0) * np.sin(TOP["psi0"]) / (TOP["C"] * TOP["r0"])
    np.testing.assert_allclose(dpsi, expected, rtol=1e-13)
    assert expected > 0

    import scipy.integrate

    K = lambda s: jnp.exp(-s) * jnp.cos(3 * s)  # noqa: E731
    ts = np.array([-40.0, 0.0, 17.0, 60.0, 100.0])
    psi, theta, r = an.lagrange_top_first_approximation(ts, **TOP, eps=eps, K=K, M3=0.3)
    F1 = [
        scipy.integrate.quad(lambda s: np.exp(-s) * np.cos(3 * s), 0, eps * t, epsabs=1e-15)[0]
        / (TOP["C"] * TOP["r0"])
        for t in ts
    ]
    expected = 2 * np.arctan(np.tan(TOP["psi0"] / 2) * np.exp(F1))
    np.testing.assert_allclose(psi, expected, atol=TIGHT)
    np.testing.assert_allclose(theta, TOP["theta0"])
    np.testing.assert_allclose(r, TOP["r0"] + 0.3 * ts / TOP["C"], atol=TIGHT)
    # ψ0 on another 2π branch, and the fixed point ψ0 = π
    top = dict(TOP, psi0=TOP["psi0"] + 4 * np.pi)
    psi_b, _, _ = an.lagrange_top_first_approximation(ts, **top, eps=eps, K=K)
    np.testing.assert_allclose(psi_b, expected + 4 * np.pi, atol=1e-12)
    top = dict(TOP, psi0=np.pi)
    psi_pi, _, _ = an.lagrange_top_first_approximation(ts, **top, eps=eps, K=K)
    np.testing.assert_allclose(psi_pi, np.pi, atol=1e-12)


def test_lagrange_second_approximation_initial_values():
    p0, q0 = 0.003, -0.002
    kw = dict(TOP, eps=0.02, K=K_of_tau, phi0=PHI0, p0=p0, q0=q0)
    psi, theta, _ = an.lagrange_top_second_approximation(jnp.zeros(1), **kw)
    np.testing.assert_allclose(psi, TOP["psi0"], atol=1e-15)
    np.testing.assert_allclose(theta, TOP["theta0"], atol=1e-15)


def test_lagrange_jit_and_vmap_over_eps():
    ts = jnp.linspace(0, 50, 11)

    def first(eps):
        return an.lagrange_top_first_approximation(ts, **TOP, eps=eps, K=K_of_tau)[0]

    def second(eps):
        return an.lagrange_top_second_approximation(ts, **TOP, eps=eps, K=K_of_tau, phi0=PHI0)[0]

    epss = jnp.array([0.01, 0.02])
    for fn in (first, second):
        batched = jax.jit(jax.vmap(fn))(epss)
        for k in range(2):
            np.testing.assert_allclose(batched[k], fn(epss[k]), atol=TIGHT)
    with pytest.raises(ValueError, match="`quad_order`"):
        an.lagrange_top_first_approximation(ts, **TOP, eps=0.1, K=K_of_tau, quad_order=0)
    with pytest.raises(ValueError, match="`r0`"):
        an.lagrange_top_first_approximation(ts, **dict(TOP, r0=jnp.ones(2)), eps=0.1, K=K_of_tau)


@pytest.mark.parametrize(
    "bad, which",
    [
        (dict(r0=0.0), "both"),
        (dict(C=0.0), "both"),
        (dict(C=-1.0), "both"),
        (dict(A=0.0), "second"),
        (dict(eps=0.0), "second"),
        (dict(theta0=0.0), "second"),
        (dict(theta0=np.pi), "second"),
    ],
)
def test_lagrange_approximations_refuse_singular_values(bad, which):
    """Values where the formulas divide by zero (`C r0`; `A`, `ε` and `sinθ0` in the second
    approximation) are refused, naming the argument, instead of returning NaN or ±inf;
    also traced, under `eqx.filter_jit`. θ0 = π in floating point has sinθ0 ≈ 1e-16, not
    0, and is refused as well. Where a formula does not divide by it the value is
    accepted."""
    (name,) = bad
    kw = dict(TOP, eps=0.02, K=K_of_tau) | bad
    ts = jnp.linspace(0.0, 10.0, 3)
    second = an.lagrange_top_second_approximation
    for fn in (an.lagrange_top_first_approximation, second):
        if which == "both" or fn is second:
            with pytest.raises(eqx.EquinoxRuntimeError, match=f"`{name}` must"):
                fn(ts, **kw)
            traced = eqx.filter_jit(lambda v, fn=fn: fn(ts, **(kw | {name: v}))[0])
            with pytest.raises(eqx.EquinoxRuntimeError, match=f"`{name}` must"):
                traced(kw[name])
        else:
            assert all(np.isfinite(x).all() for x in fn(ts, **kw))


# ---------------------------------------------------------------------------------------
# gravity gradient, integrable case A = B = m C (docs/physics.md#the-integrable-case)
# ---------------------------------------------------------------------------------------


def gg_rhs(t, y, J, eps):
    """J ω' = Jω × ω + ε γ × Jγ, γ' = γ × ω (docs/physics.md#torque-and-integrals), in
    vector form."""
    w, g = y[:3], y[3:]
    dw = (np.cross(J * w, w) + eps * np.cross(g, J * g)) / J
    return np.concatenate([dw, np.cross(g, w)])


def gg_turning(t, y, J, eps):
    """dγ''/dt = q γ − p γ' (Poisson): zero at the turning points of γ''."""
    return y[1] * y[3] - y[0] * y[4]


@pytest.mark.parametrize(
    "A, C, eps", [(1.0, 1.5, 3.0), (2.0, 1.0, 3.0), (1.0, 2.0, 0.5), (1.0, 1.2, 10.0)]
)
def test_gg_half_period_and_quartic_vs_solve_ivp(rng, A, C, eps):
    J = np.array([A, A, C])
    w0 = rng.normal(size=3)
    g0 = rng.normal(size=3)
    g0 /= np.linalg.norm(g0)
    half = an.gg_nutation_half_period(A, C, eps, w0, g0)
    sol = solve_ivp(
        gg_rhs,
        (0, 12.5 * half),
        np.r_[w0, g0],
        events=gg_turning,
        dense_output=True,
        args=(J, eps),
        **IVP,
    )
    measured = np.diff(sol.t_events[0])
    assert measured.size >= 10
    # event location on DOP853's dense output: measured ≤ 3e-12 relative
    np.testing.assert_allclose(measured, half, rtol=1e-10)
    # the quartic is (dγ''/dt)² along the numerical trajectory (measured ≤ 5e-11)
    coeffs = an.gg_nutation_quartic(A, C, eps, w0, g0)
    Y = sol.sol(np.linspace(0, 12 * half, 300))
    du = Y[1] * Y[3] - Y[0] * Y[4]
    np.testing.assert_allclose(du**2, np.polyval(coeffs, Y[5]), atol=1e-9)
    # the first integrals of the integrable case are conserved by the solver
    C1, C2, r, g2 = an.gg_integrable_case_integrals(A, C, eps, Y[:3].T, Y[3:].T)
    C10, C20, r0, _ = an.gg_integrable_case_integrals(A, C, eps, w0, g0)
    np.testing.assert_allclose(C1, C10, atol=1e-10)
    np.testing.assert_allclose(C2, C20, atol=1e-10)
    np.testing.assert_allclose(r, r0, atol=1e-10)
    np.testing.assert_allclose(g2, 1.0, atol=1e-10)


def test_gg_steady_motions():
    """γ0 = e_z, ω0 = r0 e_z: γ'' = 1 is a double root. Stable (r0²(n+1)² > 4εn): the
    small-oscillation limit, which a slightly perturbed motion (amplitude δ = 1e-3) approaches
    at O(δ²) (measured 8e-8 relative), itself checked against solve_ivp; unstable: inf."""
    A, C, eps = 1.0, 1.5, 3.0
    limit = an.gg_nutation_half_period(A, C, eps, [0, 0, 3.0], [0, 0, 1.0])
    w0 = np.array([1e-3, 0, 3.0])
    half = an.gg_nutation_half_period(A, C, eps, w0, [0, 0, 1.0])
    np.testing.assert_allclose(half, limit, rtol=1e-6)
    sol = solve_ivp(
        gg_rhs,
        (0, 10 * limit),
        np.r_[w0, 0, 0, 1.0],
        events=gg_turning,
        args=(np.array([A, A, C]), eps),
        **IVP,
    )
    # small amplitude: the event times are located to ~atol / (amplitude · frequency)
    np.testing.assert_allclose(np.diff(sol.t_events[0]), half, rtol=1e-8)
    assert an.gg_nutation_half_period(A, C, eps, [0, 0, 1.0], [0, 0, 1.0]) == math.inf


def test_gg_spherical_body_closed_form(rng):
    """A = C: no torque, ω constant, γ turns about ω: γ'' has half period π / |ω| (the
    quartic degenerates to a quadratic)."""
    w0 = rng.normal(size=3)
    g0 = rng.normal(size=3)
    g0 /= np.linalg.norm(g0)
    half = an.gg_nutation_half_period(1.3, 1.3, 3.0, w0, g0)
    np.testing.assert_allclose(half, np.pi / np.linalg.norm(w0), rtol=1e-13)


def test_gg_bad_input():
    with pytest.raises(ValueError, match="`gamma0`"):
        an.gg_nutation_half_period(1.0, 1.5, 3.0, [0.1, 0.2, 1.0], [0, 0, 2.0])
    with pytest.raises(ValueError, match="`A`"):
        an.gg_nutation_half_period(-1.0, 1.5, 3.0, [0.1, 0.2, 1.0], [0, 0, 1.0])
    with pytest.raises(ValueError, match="`omega0`"):
        an.gg_nutation_half_period(1.0, 1.5, 3.0, [0.1, 0.2], [0, 0, 1.0])


def test_gg_integrals_jit_batch(rng):
    w = rng.normal(size=(4, 3))
    g = rng.normal(size=(4, 3))
    out = jax.jit(an.gg_integrable_case_integrals)(1.0, 1.5, 3.0, w, g)
    assert all(o.shape == (4,) for o in out)
    one = an.gg_integrable_case_integrals(1.0, 1.5, 3.0, w[2], g[2])
    np.testing.assert_allclose([o[2] for o in out], one, rtol=TIGHT)
