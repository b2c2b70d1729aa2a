"""`LiePoissonSplitting`, the structure-preserving solver (docs/physics.md#geometric-integration):
its compositions' order conditions, |L| and the quaternion's norm kept to rounding, an energy
error bounded without trend, the measured order of each method, kicks of the heavy top, the
gravity-gradient body and the restoring moment's slow time, gradients against finite
differences, batches, refusals, and a scenario swept with it — at horizons CI affords
(10³–10⁴ periods; docs/performance.md#long-horizons runs them to 10⁶).

The body is the benchmarks' J (non-diagonal: the solver works in its principal frame) with
ω0 = (0.8, 0, 0.6) in principal axes: elliptic modulus k² = 0.89, period T = 29.41.
"""

import tomllib

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import load_store, random_quat, scipy_rot, small_scenario, xyzw_to_wxyz
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb
from rbdyn_jax import sweep
from rbdyn_jax.integrate._composition import COMPOSITIONS, MCLACHLAN_4, Scheme
from rbdyn_jax.integrate._exact_flows import _axis_flow, _casimir_rotation
from rbdyn_jax.scenario import SCENARIO_DIR, Scenario, ScenarioError

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
MOMENTS, AXES = np.linalg.eigh(J)
AXES = AXES * np.sign(np.linalg.det(AXES))  # right-handed
W0P = np.array([0.8, 0.0, 0.6])  # principal components
W0 = AXES @ W0P
Q0 = np.array([1.0, 0.0, 0.0, 0.0])
PERIOD = float(rb.analytic.torque_free_elliptic_period(jnp.asarray(MOMENTS), jnp.asarray(W0P)))


def state(w=W0, q=Q0):
    return rb.State(jnp.asarray(w), jnp.asarray(q))


def splitting(model, ts, order, dt, max_steps=1 << 20, y0=None):
    """A splitting solve; `dt` as an array, so that one program serves every step."""
    return rb.simulate(
        model,
        state() if y0 is None else y0,
        jnp.asarray(ts),
        solver=rb.LiePoissonSplitting(order),
        dt0=jnp.asarray(dt),
        max_steps=max_steps,
    )


def random_times(horizon, n, seed=0):
    """Sorted output times, uniform on [0, horizon] and both ends: output times
    commensurate with the period would sample the energy error at one phase of its
    oscillation only."""
    t = np.random.default_rng(seed).uniform(0.0, horizon, n)
    return np.sort(np.concatenate([[0.0, horizon], t]))


def relative(x):
    x = np.asarray(x)
    return np.abs(x / x[0] - 1.0)


def test_the_period_and_modulus_of_the_test_body():
    assert PERIOD == pytest.approx(29.41, abs=0.01)


# --------------------------------------------------------------------------------------
# The compositions
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [2, 4, 6])
def test_compositions_are_symmetric_and_meet_their_order_conditions(order):
    g = np.asarray(COMPOSITIONS[order])
    np.testing.assert_array_equal(g, g[::-1])
    # Sums of ~10 terms of size ≤ 1.2: a few float64 roundings.
    assert abs(g.sum() - 1.0) < 1e-15
    if order >= 4:
        assert abs(np.sum(g**3)) < 1e-15
    if order >= 6:
        assert abs(np.sum(g**5)) < 1e-15


def _strang(A, B, C, h):
    return expm(h * A / 2) @ expm(h * B / 2) @ expm(h * C) @ expm(h * B / 2) @ expm(h * A / 2)


def _composed(gammas, A, B, C, h):
    M = np.eye(A.shape[0])
    for g in gammas:
        M = _strang(A, B, C, g * h) @ M
    return M


@pytest.mark.parametrize("order", [2, 4, 6])
def test_compositions_have_their_order_on_a_linear_problem(order):
    """Three non-commuting linear flows, each exact (matrix exponentials): the local error
    of the composed Strang map against exp(h(A + B + C)) falls as h^(p+1). Over h = 0.1 →
    0.05 the measured slope is within 0.2 of it (asymptotic there: 2.9, 5.0 and 6.9)."""
    rng = np.random.default_rng(1)
    A, B, C = (rng.normal(size=(4, 4)) for _ in range(3))
    g = COMPOSITIONS[order]
    errs = [np.abs(_composed(g, A, B, C, h) - expm(h * (A + B + C))).max() for h in (0.1, 0.05)]
    assert np.log2(errs[0] / errs[1]) == pytest.approx(order + 1, abs=0.2)


def test_mclachlans_composition_beats_yoshidas_triple_jump():
    """The reason for McLachlan's 5 stages at order 4: a local error 37× smaller than the
    3-stage triple jump's (Yoshida 1990) on the same problem (measured; 20× required), more
    than the (5/3)⁴ ≈ 7.7 that its 5/3 cost per step takes away at equal work."""
    rng = np.random.default_rng(1)
    A, B, C = (rng.normal(size=(4, 4)) for _ in range(3))
    w1 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
    exact = expm(0.05 * (A + B + C))
    mclachlan = np.abs(_composed(MCLACHLAN_4, A, B, C, 0.05) - exact).max()
    yoshida = np.abs(_composed((w1, 1.0 - 2.0 * w1, w1), A, B, C, 0.05) - exact).max()
    assert yoshida / mclachlan > 20.0


@pytest.mark.parametrize("order", [2, 4, 6])
def test_a_schemes_flows_merge_at_the_seams_and_add_up(order):
    kicked = Scheme(
        ("kick", 0.5),
        (("0", 0.5), ("2", 1.0), ("0", 0.5), ("casimir", 1.0)),
        COMPOSITIONS[order],
        clock="2",
    )
    flows = kicked.flows()
    assert all(a[0] != b[0] for a, b in zip(flows, flows[1:]))  # merged where they meet
    for name in ("kick", "0", "2", "casimir"):  # each flow runs for one step in all
        assert sum(c for f, c, _ in flows if f == name) == pytest.approx(1.0, abs=1e-15)
    # The kicks act at t_n and at the end of each stage's free flow: t_n + (γ_1 + … + γ_i) h.
    kicks = [e for f, _, e in flows if f == "kick"]
    np.testing.assert_allclose(kicks, [0.0, *np.cumsum(COMPOSITIONS[order])], rtol=0, atol=1e-15)


# --------------------------------------------------------------------------------------
# Structure over long horizons
# --------------------------------------------------------------------------------------


def _windows(ts, err):
    """The largest error over periods 10–10² and over periods 10³–10⁴."""
    p = np.asarray(ts) / PERIOD
    return err[(p >= 10) & (p <= 100)].max(), err[(p >= 1e3) & (p <= 1e4)].max()


# Turning angles over two turns, and θ/2 within 1e-9 of π (a full turn: cos(θ/2) − 1 ≈ −2,
# where `−sin²(θ/2) / (1 + cos(θ/2))` would divide two rounding errors).
ANGLES = [0.0, 1e-9, 0.3, 2.0, np.pi, 2 * np.pi - 2e-9, 2 * np.pi, 2 * np.pi + 2e-9, 10.0]


@pytest.mark.parametrize("i", [0, 1, 2])
def test_an_axis_flow_turns_by_its_angle_at_any_angle(i):
    """`_axis_flow`'s increments, added to L and q, are the turn by θ = rate L_i about the
    principal axis i: `L ← Rot(e_i, −θ) L` and `q ← q ⊗ (cos θ/2, sin θ/2 e_i)` (scipy's
    rotations and their product, which keeps the quaternion's sign), to the rounding of
    unit-sized components (1e-15), for angles over two turns, a full turn per step
    included."""
    rng = np.random.default_rng(i)
    L, q = rng.normal(size=3), random_quat(rng)
    e = np.eye(3)[i]
    for theta in ANGLES:
        dL, dq = _axis_flow(i, jnp.asarray(L), jnp.asarray(q), jnp.asarray(theta / L[i]))
        new_L = L + np.array([float(dL[j]) if j in dL else 0.0 for j in range(3)])
        np.testing.assert_allclose(
            new_L, Rotation.from_rotvec(-theta * e).apply(L), rtol=0, atol=1e-14
        )
        want = xyzw_to_wxyz((scipy_rot(q) * Rotation.from_rotvec(theta * e)).as_quat())
        new_q = q + np.array([float(x) for x in dq])
        np.testing.assert_allclose(new_q, want, rtol=0, atol=1e-15, err_msg=theta)


def test_the_casimirs_rotation_is_exact_at_any_angle():
    """`_casimir_rotation`'s quaternion of the turn by φ = rate |L| about L, and its
    increment from the identity, at the same angles: `(cos φ/2, sin φ/2 L/|L|)` to 1e-15,
    and the increment's scalar `cos φ/2 − 1` to its own rounding (relative 1e-14, against
    `−2 sin²(φ/4)`), at a tiny angle as near a full turn; at L = 0 the identity."""
    L = np.array([0.3, -1.2, 0.7])
    n = np.linalg.norm(L)
    for phi in ANGLES:
        want = np.concatenate([[np.cos(phi / 2)], np.sin(phi / 2) * L / n])
        rate = jnp.asarray(phi / n)
        whole = np.array([float(x) for x in _casimir_rotation(jnp.asarray(L), rate, False)])
        step = np.array([float(x) for x in _casimir_rotation(jnp.asarray(L), rate, True)])
        np.testing.assert_allclose(whole, want, rtol=0, atol=1e-15, err_msg=phi)
        np.testing.assert_allclose(step + [1, 0, 0, 0], want, rtol=0, atol=1e-15, err_msg=phi)
        # the increment `cos φ/2 − 1` to its own rounding, small or not: −2 sin²(φ/4)
        np.testing.assert_allclose(step[0], -2 * np.sin(phi / 4) ** 2, rtol=1e-14, atol=0)
    zero = _casimir_rotation(jnp.zeros(3), jnp.asarray(0.5), True)
    assert [float(x) for x in zero] == [0.0, 0.0, 0.0, 0.0]


def test_free_body_over_ten_thousand_periods():
    """Order 6 at T/50, 5·10⁵ steps: the inertial angular momentum R(q) J ω (the vector,
    which sees the attitude, not only its norm) and the quaternion's norm (before the
    output's renormalisation: `norm_drift`) move by rounding only, measured 3e-15 and 1e-15
    (tolerance 1e-13: the compensated sums leave a random walk of a small fraction of an
    ulp per step; summed plainly they reach 1e-13 here); the energy error,
    1.7e-9 here, shows no trend: its largest value over periods 10³–10⁴ is within 2× of
    that over periods 10–10² (1.0002× measured; a drift of the energy grows linearly: 98×
    between the windows for Tsit5 at rtol 1e-8, checked below)."""
    ts = random_times(1e4 * PERIOD, 4000)
    model = rb.RigidBody(jnp.asarray(J))
    traj = splitting(model, ts, 6, PERIOD / 50)
    L = np.asarray(rb.invariants.angular_momentum_inertial(model, traj))
    assert np.abs(L - L[0]).max() / np.linalg.norm(L[0]) < 1e-13
    assert float(traj.stats["norm_drift"]) < 1e-13
    energy = relative(rb.invariants.energy(model, traj))
    early, late = _windows(ts, energy)
    assert energy.max() < 1e-8 and late < 2.0 * early
    adaptive = rb.simulate(model, state(), jnp.asarray(ts), rtol=1e-8, atol=1e-8, max_steps=1 << 21)
    early, late = _windows(ts, relative(rb.invariants.energy(model, adaptive)))
    assert late > 20.0 * early  # the criterion sees a drift


@pytest.mark.parametrize("torque", ["heavy_top", "gravity_gradient"])
def test_potential_torques_keep_the_energy_bounded(torque):
    """The heavy top (weight 1 at r_c = (0, 0, 0.5)) and the gravity-gradient body (ε = 3)
    of the benchmarks, order 4 at dt = 0.05 over t ≤ 10⁴ (about 1600 and 3000 of their
    fastest periods): kicks L ← L + h M(q) keep the energy error bounded (measured 1.9e-9
    and 4.6e-8; the largest over t ∈ [5000, 10⁴] within 1.01× of that over [100, 1000]:
    tolerance 2×), the quaternion's norm to rounding (1e-15 measured, 1e-13 allowed) and
    the heavy top's vertical angular momentum to rounding."""
    tq = (
        rb.UniformGravity(1.0, jnp.array([0.0, 0.0, 0.5]))
        if torque == "heavy_top"
        else rb.GravityGradient(3.0)
    )
    model = rb.RigidBody(jnp.asarray(J), tq)
    y0 = state(W0, rb.rotation.euler_to_quat(jnp.array([0.3, 0.7, 0.2]), "ZXZ"))
    ts = random_times(1e4, 3000)
    traj = splitting(model, ts, 4, 0.05, y0=y0)
    energy = relative(rb.invariants.energy(model, traj))
    early = energy[(ts >= 100) & (ts <= 1000)].max()
    late = energy[ts >= 5000].max()
    assert energy.max() < 1e-7 and late < 2.0 * early
    assert float(traj.stats["norm_drift"]) < 1e-13
    if torque == "heavy_top":
        # Gravity along z0 has no moment about z0: every kick and every free flow keeps the
        # vertical angular momentum L·z0, which moves by rounding only (4e-15 of |L|
        # measured; 1e-13 allowed). Tsit5 at 1e-8 lets it drift (6e-7 measured).
        def vertical(tr):
            L = np.asarray(rb.invariants.angular_momentum_inertial(model, tr))
            return np.abs(L[:, 2] - L[0, 2]).max() / np.linalg.norm(L[0])

        adaptive = rb.simulate(model, y0, jnp.asarray(ts), max_steps=1 << 20)
        assert vertical(traj) < 1e-13 and vertical(adaptive) > 1e3 * vertical(traj)


# --------------------------------------------------------------------------------------
# Orders
# --------------------------------------------------------------------------------------

# Steps per period where each method's error is asymptotic and far above rounding.
STEPS = {2: (200, 400, 800), 4: (50, 100, 200), 6: (50, 100, 200)}


@pytest.mark.parametrize("order", [2, 4, 6])
def test_measured_order_of_convergence(order):
    """Over 5 periods: the error of ω against the Jacobi elliptic solution, and of the
    attitude by Richardson's comparison of successive halvings, fall as h^p. Measured
    slopes 2.00, 4.01–4.03, 5.86–5.97; tolerance 0.25 (the next term of the error
    expansion at these steps; order 6's smallest error, 9e-11, is far above rounding)."""
    ts = np.linspace(0.0, 5.0 * PERIOD, 6)
    model = rb.RigidBody(jnp.asarray(J))
    exact = (
        AXES
        @ np.asarray(
            rb.analytic.torque_free_elliptic(
                jnp.asarray(MOMENTS), jnp.asarray(W0P), jnp.asarray(ts)
            )
        ).T
    )
    runs = [splitting(model, ts, order, PERIOD / n, max_steps=1 << 12) for n in STEPS[order]]
    err_w = [np.abs(np.asarray(r.ys.omega) - exact.T).max() for r in runs]
    q = [np.asarray(r.ys.quat) * np.sign(np.asarray(r.ys.quat)[:, :1]) for r in runs]
    err_q = [np.abs(q[0] - q[1]).max(), np.abs(q[1] - q[2]).max()]
    for e in (err_w[:2], err_w[1:], err_q):
        assert np.log2(e[0] / e[1]) == pytest.approx(order, abs=0.25)


def test_a_slowly_varying_restoring_moment_keeps_the_order():
    """k(τ, ψ) = ε K(τ) sin ψ with τ = ε t (ε = 0.5: the time dependence matters over the
    horizon): the kicks see the time at which they act, so order 4 stays order 4 (a kick
    at a wrong time would make it order 1). Richardson's comparison of ω and the attitude
    over halvings; measured 3.99–4.00; tolerance 0.25."""
    k = rb.PolynomialSinPsi(jnp.array([1.0, 2.0]), 0.5)
    model = rb.RigidBody(jnp.diag(jnp.array([1.0, 1.0, 1.5])), rb.RestoringMoment(k))
    y0 = state(
        np.array([0.1, 0.0, 3.0]), rb.rotation.euler_to_quat(jnp.array([1.0, 0.8, 0.3]), "ZXZ")
    )
    ts = np.linspace(0.0, 4.0, 5)
    runs = [splitting(model, ts, 4, 4.0 / n, max_steps=1 << 12, y0=y0) for n in (50, 100, 200)]
    ys = [np.concatenate([np.asarray(r.ys.omega), np.asarray(r.ys.quat)], axis=-1) for r in runs]
    e = [np.abs(ys[0] - ys[1]).max(), np.abs(ys[1] - ys[2]).max()]
    assert np.log2(e[0] / e[1]) == pytest.approx(4.0, abs=0.25)


def _reference(model, y0, ts):
    """Dopri8 at rtol = atol = 1e-13: ω and q to about 1e-11 over these short horizons."""
    return rb.simulate(
        model,
        y0,
        jnp.asarray(ts),
        solver=diffrax.Dopri8(),
        rtol=1e-13,
        atol=1e-13,
        max_steps=1 << 16,
    )


def _aligned(q):
    q = np.asarray(q)
    return q * np.sign(q[:, :1])


@pytest.mark.parametrize("torque", ["free", "restoring", "body", "sum"])
def test_states_match_an_adaptive_reference_from_a_later_start(torque):
    """ω and the attitude against Dopri8 at 1e-13 over t ∈ [1, 6] (a start other than 0,
    so that the kicks' times and the deferred Casimir rotation are checked in the solve's
    own time): the free body of the test inertia, the slowly varying restoring moment
    k(τ, ψ) = ε K(τ) sin ψ (ε = 0.5), a constant body-fixed moment, and the heavy top plus
    the gravity gradient plus a constant moment fixed in space. Order 6 at dt = 0.01: the
    differences, 3e-12 to 8e-12 measured, are the reference's own error (they do not change
    at dt = 0.1 for the free body); 1e-10 allowed, where a wrong sign of a flow or a kick
    at a wrong time would leave errors of order 1e-3 or more."""
    I3 = jnp.asarray(J)
    models = {
        "free": rb.RigidBody(I3),
        "restoring": rb.RigidBody(
            jnp.diag(jnp.array([1.0, 1.0, 1.5])),
            rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([1.0, 2.0]), 0.5)),
        ),
        "body": rb.RigidBody(I3, rb.BodyTorque(jnp.array([0.1, -0.2, 0.05]))),
        "sum": rb.RigidBody(
            I3,
            rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5]))
            + rb.GravityGradient(0.7)
            + rb.InertialTorque(jnp.array([0.05, 0.0, -0.1])),
        ),
    }
    model = models[torque]
    y0 = state(
        W0 if torque != "restoring" else np.array([0.1, 0.0, 3.0]),
        rb.rotation.euler_to_quat(jnp.array([1.0, 0.8, 0.3]), "ZXZ"),
    )
    ts = np.linspace(1.0, 6.0, 6)
    ref = _reference(model, y0, ts)
    traj = splitting(model, ts, 6, 0.01, max_steps=1 << 12, y0=y0)
    assert np.abs(np.asarray(traj.ys.omega) - np.asarray(ref.ys.omega)).max() < 1e-10
    assert np.abs(_aligned(traj.ys.quat) - _aligned(ref.ys.quat)).max() < 1e-10


def test_a_moment_fixed_in_space_adds_to_the_angular_momentum_linearly():
    """Under a constant moment M0 fixed in space, dL/dt = M0 in the inertial frame: L(t) =
    L(t0) + M0 (t − t0) exactly. The kicks add h R(q)ᵀ M0 in body axes, h M0 in space, and
    the free flows keep the inertial L, so the splitting holds this closed form to rounding
    at any step (order 2, dt = 0.1 over 10³ time units: measured 3e-15 of |L|; 1e-12
    allowed), though its attitude is only of order 2."""
    M0 = np.array([0.02, -0.01, 0.03])
    model = rb.RigidBody(jnp.asarray(J), rb.InertialTorque(jnp.asarray(M0)))
    ts = random_times(1e3, 500)
    traj = splitting(model, ts, 2, 0.1)
    L = np.asarray(rb.invariants.angular_momentum_inertial(model, traj))
    exact = L[0] + np.outer(ts - ts[0], M0)
    assert np.abs(L - exact).max() / np.linalg.norm(exact, axis=-1).max() < 1e-12


# --------------------------------------------------------------------------------------
# Gradients, batches, diffeqsolve
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("torque", ["free", "gravity_gradient"])
def test_gradients_match_finite_differences(torque):
    """jax.grad through the solve (diffrax's RecursiveCheckpointAdjoint) of a loss on the
    final state of the torque-free body (its Casimir flow deferred to the outputs) and of
    the gravity-gradient body (kicked), with respect to the inertia and the initial rates
    and attitude, against central differences (step 1e-6: truncation ~1e-12, rounding
    ~1e-10 of a loss of order 1; agreement to 1e-7 relative)."""
    ts = jnp.linspace(0.0, 3.0, 3)

    def loss(J, w, q):
        model = rb.RigidBody(J, None if torque == "free" else rb.GravityGradient(0.5))
        traj = rb.simulate(model, rb.State(w, q), ts, solver=rb.LiePoissonSplitting(4), dt0=0.25)
        return jnp.sum(traj.ys.omega[-1] ** 2) + jnp.dot(
            traj.ys.quat[-1], jnp.array([0.1, 0.2, 0.3, 0.4])
        )

    args = (
        jnp.asarray(J),
        jnp.asarray(W0 + 0.1),
        rb.rotation.quat_normalize(jnp.array([0.9, 0.1, -0.2, 0.3])),
    )
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*args)
    eps = 1e-6
    rng = np.random.default_rng(2)
    for i, g in enumerate(grads):
        d = rng.normal(size=g.shape)
        if i == 0:
            d = d + d.T  # a symmetric perturbation of the inertia
        up = list(args)
        down = list(args)
        up[i] = args[i] + eps * d
        down[i] = args[i] - eps * d
        fd = (loss(*up) - loss(*down)) / (2 * eps)
        assert float(jnp.sum(g * d)) == pytest.approx(float(fd), rel=1e-7, abs=1e-9)


def test_a_batch_under_vmap_equals_the_trajectories_one_by_one():
    """`simulate_batch` takes `Vmap` for the splitting (every trajectory steps in
    lockstep, fixed steps waste nothing); its trajectories, over initial states and over
    a batch of models, equal `simulate`'s to rounding (XLA vectorises the batch: 1e-13)."""
    ts = jnp.linspace(0.0, 20.0, 5)
    rates = np.random.default_rng(3).normal(size=(3, 3))
    y0s = rb.State(jnp.asarray(rates), jnp.tile(jnp.asarray(Q0), (3, 1)))
    Js = jnp.stack([jnp.asarray(J) * s for s in (1.0, 1.1, 0.9)])
    models = eqx.filter_vmap(lambda J: rb.RigidBody(J, rb.GravityGradient(0.3)))(Js)
    solver = rb.LiePoissonSplitting(4)
    batch = rb.simulate_batch(models, y0s, ts, model_axes=0, solver=solver, dt0=0.1)
    assert np.all(np.asarray(rb.integrate.result_code(batch.result)) == 0)
    for i in range(3):
        one = rb.simulate(
            rb.RigidBody(Js[i], rb.GravityGradient(0.3)),
            rb.State(y0s.omega[i], y0s.quat[i]),
            ts,
            solver=solver,
            dt0=0.1,
        )
        np.testing.assert_allclose(batch.ys.omega[i], one.ys.omega, rtol=0, atol=1e-13)
        np.testing.assert_allclose(batch.ys.quat[i], one.ys.quat, rtol=0, atol=1e-13)
        assert int(batch.stats["num_steps"][i]) == int(one.stats["num_steps"]) == 200


def test_lanes_refuse_the_splitting_and_name_vmap():
    y0s = rb.State(jnp.asarray(np.tile(W0, (2, 1))), jnp.tile(jnp.asarray(Q0), (2, 1)))
    with pytest.raises(ValueError, match=r"`Lanes` .*LiePoissonSplitting.*Vmap\(\)"):
        rb.simulate_batch(
            rb.RigidBody(jnp.asarray(J)),
            y0s,
            jnp.linspace(0.0, 1.0, 3),
            solver=rb.LiePoissonSplitting(),
            dt0=0.1,
            batching=rb.Lanes(),
        )


@pytest.mark.parametrize("torque", ["free", "heavy_top"])
def test_diffeqsolve_takes_the_models_field_and_runs_backwards_to_the_start(torque):
    """With `diffrax.ODETerm(model.vector_field)` the solver finds the model itself. The
    method is symmetric, Φ(−h) = Φ(h)⁻¹: from t = 0 to 5 and back (diffeqsolve's reversed
    time) returns to the start to rounding (1e-14 measured; tolerance 1e-12), the free
    body's deferred Casimir rotation included."""
    tq = None if torque == "free" else rb.UniformGravity(1.0, jnp.array([0.0, 0.0, 0.5]))
    model = rb.RigidBody(jnp.asarray(J), tq)
    term = diffrax.ODETerm(model.vector_field)
    solver = rb.LiePoissonSplitting(6)
    y0 = state()
    out = diffrax.diffeqsolve(
        term, solver, jnp.asarray(0.0), jnp.asarray(5.0), jnp.asarray(0.1), y0
    )
    back = diffrax.diffeqsolve(
        term,
        solver,
        jnp.asarray(5.0),
        jnp.asarray(0.0),
        jnp.asarray(-0.1),
        jax.tree_util.tree_map(lambda x: x[-1], out.ys),
    )
    assert np.abs(np.asarray(out.ys.omega[-1]) - W0).max() > 0.01  # it moved
    np.testing.assert_allclose(back.ys.omega[-1], W0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.ys.quat[-1], Q0, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="needs the rigid-body model behind the term"):
        diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: model.vector_field(t, y, args)),
            solver,
            0.0,
            1.0,
            0.1,
            y0,
        )


# --------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------

JJ = jnp.asarray(J)
REFUSED = {
    "RelativeRigidBody": rb.RelativeRigidBody(
        JJ, rb.ConstantRate(jnp.array([0.0, 0.0, 1.0])), rb.BalancingTransport()
    ),
    "PoissonRigidBody": rb.PoissonRigidBody(JJ),
    "EulerAngleRigidBody": rb.EulerAngleRigidBody(JJ),
}


@pytest.mark.parametrize("name", REFUSED)
def test_a_model_it_cannot_split_is_refused_by_name(name):
    with pytest.raises(ValueError, match=rf"cannot integrate .*`{name}`.*adaptive solver"):
        rb.simulate(
            REFUSED[name],
            state(),
            jnp.linspace(0.0, 1.0, 3),
            solver=rb.LiePoissonSplitting(),
            dt0=0.1,
        )


def test_balancing_transport_and_a_torque_of_ones_own_are_refused():
    class Damping(rb.AbstractTorque):
        def __call__(self, kin, inertia):
            return -kin.omega

    for torque, name in ((rb.BalancingTransport(), "BalancingTransport"), (Damping(), "Damping")):
        with pytest.raises(ValueError, match=rf"the torque `{name}`"):
            rb.LiePoissonSplitting().check_model(rb.RigidBody(JJ, torque))
    rb.LiePoissonSplitting().check_model(
        rb.RigidBody(
            JJ,
            rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([1.0]), 0.1))
            + rb.UniformGravity(1.0, jnp.ones(3))
            + rb.BodyTorque(jnp.ones(3))
            + rb.InertialTorque(jnp.ones(3)),
        )
    )


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"rtol": 1e-8}, "`rtol` and `atol` mean nothing"),
        ({"dt0": None}, "`dt0` is the fixed step"),
        ({"dt0": -0.1}, "`dt0` must be a positive step"),
        ({"max_steps": 5}, r"`max_steps` = 5 is fewer than the 10 steps"),
        ({"stepsize_controller": diffrax.PIDController(rtol=1e-6, atol=1e-6)}, "fixed steps"),
    ],
)
def test_settings_a_fixed_step_solver_cannot_take_are_refused(settings, message):
    kwargs = {"dt0": 0.1, **settings}
    with pytest.raises(ValueError, match=message):
        rb.simulate(
            rb.RigidBody(JJ),
            state(),
            jnp.linspace(0.0, 1.0, 3),
            solver=rb.LiePoissonSplitting(),
            **kwargs,
        )


def test_order_must_be_two_four_or_six():
    for order in (1, 3, 8, True):
        with pytest.raises(ValueError, match="`order` must be one of"):
            rb.LiePoissonSplitting(order)


# --------------------------------------------------------------------------------------
# Scenarios and sweeps
# --------------------------------------------------------------------------------------


def _splitting_scenario(**solver):
    return small_scenario(solver={"method": "LiePoissonSplitting", "dt": 0.01, **solver})


def test_a_scenario_takes_the_splitting_with_its_step():
    sc = Scenario.from_dict(_splitting_scenario(order=4))
    assert isinstance(sc.diffrax_solver, rb.LiePoissonSplitting)
    assert sc.diffrax_solver.order(None) == 4
    assert isinstance(sc.stepsize_controller, diffrax.ConstantStepSize)
    assert (sc.dt, sc.max_steps, sc.fixed_step) == (0.01, 401, True)
    assert Scenario.from_dict(small_scenario()).dt is None


@pytest.mark.parametrize(
    "solver, key",
    [
        ({"rtol": 1e-8}, "solver.rtol"),
        ({"dt": None}, "solver.dt"),
        ({"dt": 10.0}, "solver.dt"),
        ({"order": 5}, "solver.order"),
        ({"max_steps": 10}, "solver.max_steps"),
    ],
)
def test_a_splitting_scenario_names_its_bad_key(solver, key):
    d = _splitting_scenario(**solver)
    d["solver"] = {k: v for k, v in d["solver"].items() if v is not None}
    with pytest.raises(ScenarioError, match=rf"`{key}`"):
        Scenario.from_dict(d)


def test_a_scenario_refuses_the_splitting_for_a_model_it_cannot_split():
    d = tomllib.loads((SCENARIO_DIR / "rotating_platform.toml").read_text())
    d["solver"] = {"method": "LiePoissonSplitting", "dt": 0.01}
    with pytest.raises(ScenarioError, match=r"`solver.method`: .*`RelativeRigidBody`"):
        Scenario.from_dict(d)
    d = small_scenario(solver={"method": "Tsit5", "dt": 0.1})
    with pytest.raises(ScenarioError, match="`solver.dt`"):
        Scenario.from_dict(d)


def test_a_sweep_with_the_splitting_matches_simulate(tmp_path):
    """`sweep.run` of a scenario with `[solver] method = "LiePoissonSplitting"`: every
    trajectory solved (status 0, 400 steps of dt = 0.01 over t ≤ 4), its states those of
    `simulate` from the stored inertia and initial state (to 1e-13: the batch is
    vectorised), its energy drift the method's (order 6 at dt = 0.01 on rates of order 1:
    below 1e-12).

    Needs `sweep` to pass the scenario's `dt` as `dt0` and to batch a fixed-step method with
    `Vmap` (`Lanes` refuses it)."""
    sc = Scenario.from_dict(_splitting_scenario())
    out = sweep.run(sc, 6, tmp_path / "s.zarr", chunk=6, seed=1, lanes=4)
    store = load_store(out)
    assert np.all(store["status"] == 0) and np.all(store["num_steps"] == 400)
    assert np.all(np.abs(store["energy_drift"]) < 1e-12)
    for i in (0, 5):
        one = rb.simulate(
            rb.RigidBody(jnp.asarray(store["inertia"][i])),
            rb.State(jnp.asarray(store["omega"][i, 0]), jnp.asarray(store["quat"][i, 0])),
            jnp.asarray(sc.ts),
            solver=sc.diffrax_solver,
            dt0=sc.dt,
            max_steps=sc.max_steps,
        )
        np.testing.assert_allclose(store["omega"][i], one.ys.omega, rtol=0, atol=1e-13)
        np.testing.assert_allclose(store["quat"][i], one.ys.quat, rtol=0, atol=1e-13)
