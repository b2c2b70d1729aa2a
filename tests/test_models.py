"""Models and solves against independent references (the physics guide, docs/physics.md).

The torques and frames the models use are tested on their own in test_torques.py and
test_frames.py. References that cannot be wrong in the same way as the library:

- the kinematics record a torque sees (relative ω, ω_e, ε_e, γ, attitudes) recomputed with
  scipy attitudes and hand derivatives of the frame angles;
- relative motion (docs/physics.md#relative-motion): the same physical motion solved in
  absolute terms by `RigidBody`;
- first integrals of relative motion, the restoring moment and the gravity gradient, and the
  closed forms of the pitch libration (docs/physics.md#pitch-libration: linear frequency, and
  the exact pendulum period through the complete elliptic integral K).

Solver tolerances. Unless said otherwise solves run Tsit5 at rtol = atol = 1e-10 on O(1)
states over O(10) time units. Local error control keeps each step's error ≲ 1e-10 and the
global error after a few hundred steps is ~1e-9–1e-8; comparisons of two independent solves
use 1e-8 (~100 × rtol) and first integrals, which drift more slowly than the state, use
bounds stated at each test. Finite differences use central steps h with truncation error
~h²·|f'''| and rounding ~1e-16/h (h = 1e-5 ⇒ both ≲ 1e-10).

Compile time dominates: `simulate` is compiled once per model *structure* (and output-grid
length), so each structure below is solved with several parameter values but one grid size.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    E_Z,
    FD_TOL,
    FRAME_C,
    TIGHT,
    PolyAngles,
    assert_quat_equal,
    frame_omega1,
    frame_rot,
    general_inertia,
    host_callbacks,
    random_quat,
    relative_setup,
    scipy_rot,
    xyzw_to_wxyz,
    zxz,
)
from scipy.spatial.transform import Rotation
from scipy.special import ellipk

import rbdyn_jax as rb

RTOL = ATOL = 1e-10
# Two independent solves of the same motion at rtol = atol = 1e-10 (~100 × rtol).
SOLVE_TOL = 1e-8

N_OUT = 101  # one output-grid length for every solve of a structure (one compile each)

# Bounded rates for long runs: (0.3 t + 0.5 sin t, 0.6 + 0.2 sin t, −0.5 t + 0.8 sin t).
FRAME_C_LONG = np.array([[0.0, 0.3, 0.0, 0.5], [0.6, 0.0, 0.0, 0.2], [0.0, -0.5, 0.0, 0.8]])


# ------------------------------------------------------------------------------------------
# solves and first integrals
# ------------------------------------------------------------------------------------------


def ts_grid(T, n=N_OUT):
    return jnp.linspace(0.0, T, n)


def solve(model, y0, T, t0=0.0, **kw):
    traj = rb.simulate(model, y0, t0 + ts_grid(T, kw.pop("n", N_OUT)), rtol=RTOL, atol=ATOL, **kw)
    assert traj.result == rb.RESULTS.successful
    return traj


def rel_drift(x):
    x = np.asarray(x)
    return float(np.max(np.abs(x - x[0])) / max(1.0, abs(x[0])))


_INVARIANTS = {}


def invariant(name, model, traj):
    """`rb.invariants.<name>(model, traj)`, jitted once per invariant."""
    if name not in _INVARIANTS:
        _INVARIANTS[name] = eqx.filter_jit(getattr(rb.invariants, name))
    return jax.tree_util.tree_map(np.asarray, _INVARIANTS[name](model, traj))


def gravity(eps=0.0, weight=0.0, com=(0.0, 0.0, 0.0)):
    """GravityGradient + UniformGravity: one torque *structure* for the absolute solves of the
    heavy top and the gravity gradient, so that RigidBody / EulerAngleRigidBody /
    PoissonRigidBody each compile once; a zero `eps` or `weight` switches a part off (its moment
    and potential vanish)."""
    return rb.GravityGradient(eps) + rb.UniformGravity(weight, jnp.asarray(com))


# ------------------------------------------------------------------------------------------
# 1. The kinematics record of a relative model (what its torques see)
# ------------------------------------------------------------------------------------------


@pytest.fixture
def rel_setup(rng):
    """A relative model under a time-varying ZXZ frame, a random state and time, with every
    quantity a torque sees recomputed independently (`helpers.relative_setup`)."""
    return relative_setup(rng)


def test_relative_kinematics_record(rel_setup):
    model, kin, ref = rel_setup
    np.testing.assert_allclose(kin.omega_e, ref["w_e"], atol=FD_TOL)
    np.testing.assert_allclose(kin.eps_e, ref["e_e"], atol=FD_TOL)
    np.testing.assert_allclose(kin.omega_r, ref["w_r"], atol=TIGHT)
    np.testing.assert_allclose(kin.omega, ref["w_r"] + ref["w_e"], atol=FD_TOL)
    np.testing.assert_allclose(kin.gamma, ref["gamma"], atol=TIGHT)
    np.testing.assert_allclose(kin.gamma_inertial, ref["gamma0"], atol=TIGHT)
    assert_quat_equal(kin.quat, ref["q_r"], atol=TIGHT)
    assert_quat_equal(kin.quat_inertial, ref["q_abs"], atol=TIGHT)


# ------------------------------------------------------------------------------------------
# 2. Relative motion reproduces the absolute motion (docs/physics.md#relative-motion)
# ------------------------------------------------------------------------------------------

REL_T = 8.0


def _absolute_reference(rng, frame_rot_fn, frame_w1_fn, make_rel, t0=0.0):
    """Solve the relative model and the absolute one from the same physical initial state
    at `t0`, and map the absolute solution into the frame with independent (scipy / FD)
    frame data."""
    J = general_inertia(rng, [1.0, 1.6, 2.3])
    M0 = rng.normal(size=3)
    mg, r_c = 1.2, rng.normal(size=3)
    results = {}
    # Zero parameters make the first case torque-free (NoTorque physically) with the same
    # structure as the second, so both reuse one compiled solve per model class.
    for label, torque in [
        ("torque-free", rb.InertialTorque(np.zeros(3)) + rb.UniformGravity(0.0, r_c)),
        ("inertial+gravity", rb.InertialTorque(M0) + rb.UniformGravity(mg, r_c)),
    ]:
        rel = make_rel(J, torque)
        w_r0, q_r0 = rng.normal(size=3), random_quat(rng)
        traj_r = solve(rel, rb.State(jnp.asarray(w_r0), jnp.asarray(q_r0)), REL_T, t0)
        # ω = ω_r + R_rᵀ ω_e¹, q_abs = q_e(t0) ⊗ q_r at t = t0
        Rr0, Re0 = scipy_rot(q_r0), frame_rot_fn(t0)
        w0 = w_r0 + Rr0.inv().apply(frame_w1_fn(t0))
        q_abs0 = xyzw_to_wxyz((Re0 * Rr0).as_quat())
        traj_a = solve(
            rb.RigidBody(J, torque), rb.State(jnp.asarray(w0), jnp.asarray(q_abs0)), REL_T, t0
        )
        w_err = q_err = 0.0
        for i, t in enumerate(np.asarray(traj_a.ts)):
            Rr = frame_rot_fn(t).inv() * scipy_rot(traj_a.ys.quat[i])
            w_r = np.asarray(traj_a.ys.omega[i]) - Rr.inv().apply(frame_w1_fn(t))
            q_r = xyzw_to_wxyz(Rr.as_quat())
            np.testing.assert_allclose(traj_r.ys.omega[i], w_r, atol=SOLVE_TOL)
            assert_quat_equal(traj_r.ys.quat[i], q_r, atol=SOLVE_TOL)
            w_err = max(w_err, np.max(np.abs(traj_r.ys.omega[i] - w_r)))
            q_err = max(
                q_err, np.min([np.max(np.abs(traj_r.ys.quat[i] - s * q_r)) for s in (1, -1)])
            )
        results[label] = (w_err, q_err)
        # the frame really matters: ω_r differs from ω by O(1)
        assert np.max(np.abs(np.asarray(traj_r.ys.omega) - np.asarray(traj_a.ys.omega))) > 0.1
    return results


def test_relative_under_euler_angle_frame_reproduces_absolute_motion(rng):
    """Mukhametzyanov (2009), eq. (11), in a frame with time-varying ω_e and ε_e (the ZXZ angles
    of `helpers.FRAME_C`) and a general J: ω_r(t) = ω(t) − R_rᵀ ω_e¹(t) and
    q_r(t) = q_e(t)* ⊗ q(t) with (ω, q) from Euler's absolute equations, at every output time,
    to 1e-8 (~100 × rtol)."""
    frame = rb.EulerAngleFrame(PolyAngles(jnp.asarray(FRAME_C)), seq="ZXZ")
    errs = _absolute_reference(
        rng,
        lambda t: frame_rot(FRAME_C, "ZXZ", t),
        lambda t: frame_omega1(FRAME_C, "ZXZ", t),
        lambda J, torque: rb.RelativeRigidBody(J, frame, torque),
    )
    print("relative vs absolute, EulerAngleFrame ZXZ (max |Δω_r|, max |Δq_r|):", errs)


def test_relative_motion_from_a_later_start_time(rng):
    """The same check from t0 = 1.3 (`ts` = t0 + [0, 8]; 2.4e-9 seen, bound 1e-8 as above:
    the frame's rates grow with t, and from t0 = 3.7 the error reached 9.7e-9, before and
    after the unit time). The solves run in the unit time s = (t − t0)/span
    (`integrate._unit_time`), and the frame must be read at t = t0 + s·span: a solve that
    dropped t0 reads the frame's time-varying angles at the wrong times (this test then
    fails, checked)."""
    frame = rb.EulerAngleFrame(PolyAngles(jnp.asarray(FRAME_C)), seq="ZXZ")
    errs = _absolute_reference(
        rng,
        lambda t: frame_rot(FRAME_C, "ZXZ", t),
        lambda t: frame_omega1(FRAME_C, "ZXZ", t),
        lambda J, torque: rb.RelativeRigidBody(J, frame, torque),
        t0=1.3,
    )
    print("relative vs absolute from t0 = 1.3 (max |Δω_r|, max |Δq_r|):", errs)


def test_relative_under_constant_rate_frame_reproduces_absolute_motion(rng):
    w_e = np.array([0.4, -0.7, 0.9])
    q0 = random_quat(rng)
    frame = rb.ConstantRate(w_e, quat0=q0)
    errs = _absolute_reference(
        rng,
        lambda t: scipy_rot(q0) * Rotation.from_rotvec(w_e * t),
        lambda t: w_e,
        lambda J, torque: rb.RelativeRigidBody(J, frame, torque),
    )
    print("relative vs absolute, ConstantRate (max |Δω_r|, max |Δq_r|):", errs)


# ------------------------------------------------------------------------------------------
# 3. Balanced transport conserves the relative kinetic energy
#    (docs/physics.md#balancing-transport-moment)
# ------------------------------------------------------------------------------------------


def test_balanced_transport_conserves_relative_kinetic_energy(rng):
    """Mukhametzyanov (2009), §4: M = J ε_e − J ω_e × ω_e ⇒ T_r = ½ ω_rᵀ J ω_r constant under
    any transport, and |ω_r| ∈ [sqrt(2T_r/C), sqrt(2T_r/A)] (eq. (18)).

    Drift bound: each accepted Tsit5 step changes T_r by at most its local error, held at
    ~rtol·|y| = 1e-10 for O(1) states; a few thousand steps over t ∈ [0, 200] accumulate at
    most ~steps × 1e-10 if every error had one sign (≈ 1e-7 here), ~√steps × 1e-10 if random.
    The assertion uses the worst case computed from the solver's own step count.
    """
    moments = np.array([1.0, 1.7, 2.4])
    J = general_inertia(rng, moments)
    frame = rb.EulerAngleFrame(PolyAngles(jnp.asarray(FRAME_C_LONG)), seq="ZXZ")
    model = rb.RelativeRigidBody(J, frame, rb.BalancingTransport())
    w_r0 = np.array([0.6, -0.9, 0.5])
    traj = rb.simulate(
        model,
        rb.State(jnp.asarray(w_r0), jnp.asarray(random_quat(rng))),
        jnp.linspace(0.0, 200.0, 401),
        rtol=RTOL,
        atol=ATOL,
        max_steps=65_536,
    )
    assert traj.result == rb.RESULTS.successful
    Tr = np.asarray(invariant("relative_kinetic_energy", model, traj))
    drift = rel_drift(Tr)
    steps = int(traj.stats["num_accepted_steps"])
    print(f"balanced transport: T_r relative drift {drift:.2e} over t ∈ [0, 200], {steps} steps")
    assert drift <= steps * RTOL
    np.testing.assert_allclose(Tr[0], 0.5 * w_r0 @ J @ w_r0, rtol=TIGHT)
    speed = np.linalg.norm(np.asarray(traj.ys.omega), axis=-1)
    lo, hi = np.sqrt(2 * Tr[0] / moments[2]), np.sqrt(2 * Tr[0] / moments[0])
    assert np.all(speed >= lo * (1 - 1e-8)) and np.all(speed <= hi * (1 + 1e-8))
    # the hodograph really moves over the ellipsoid (ω_r is far from stationary)
    assert speed.max() - speed.min() > 0.2 * (hi - lo)
    # and the absolute kinetic energy is not conserved: the frame does work on the body
    T = np.asarray(invariant("kinetic_energy", model, traj))
    assert rel_drift(T) > 1e-2


# ------------------------------------------------------------------------------------------
# 4. Heavy (Lagrange) top
# ------------------------------------------------------------------------------------------


def test_heavy_top_first_integrals_and_precession(rng):
    """Lagrange top (docs/physics.md#equations-of-motion): J = diag(A, A, C), com on the axis.
    Energy, the area integral L_z = (J ω)·γ and the spin r are first integrals; a fast top
    released with ψ' = θ' = 0 precesses on average at ψ' ≈ k/(C r) (k = m g l), in the positive
    sense.

    Bounds: the integrals drift ≤ 1e-8 (~100 × rtol over ~1000 steps, see the module
    docstring; a sign error in the torque or its potential gives O(1)); the precession rate is
    a first approximation with relative error O(A k/(C r)²) ≈ 2 % plus the nutation left in
    a window of ~15 nutation periods, ≲ 1 %; 5 % is asserted.
    """
    A, C, mg, l, r0 = 1.0, 1.6, 1.0, 0.5, 3.0
    model = rb.RigidBody(jnp.diag(jnp.array([A, A, C])), gravity(weight=mg, com=(0.0, 0.0, l)))
    q0 = Rotation.from_euler("ZXZ", [0.2, 0.5, -0.3])
    traj = solve(
        model, rb.State(jnp.array([0.0, 0.0, r0]), jnp.asarray(xyzw_to_wxyz(q0.as_quat()))), 20.0
    )
    E = invariant("energy", model, traj)
    Lz = invariant("area_integral", model, traj)
    r = traj.ys.omega[:, 2]
    drifts = [rel_drift(E), rel_drift(Lz), rel_drift(r)]
    print("heavy top drifts (E, L_z, r):", drifts, traj.stats["num_accepted_steps"], "steps")
    assert max(drifts) <= SOLVE_TOL
    # L_z computed independently: z0 component of R(q) J ω
    Lz_ref = [
        (scipy_rot(q).apply(np.diag([A, A, C]) @ np.asarray(w)))[2]
        for q, w in zip(np.asarray(traj.ys.quat), np.asarray(traj.ys.omega))
    ]
    np.testing.assert_allclose(Lz, Lz_ref, atol=TIGHT)
    psi = np.unwrap(zxz(traj.ys.quat)[:, 0])
    rate = (psi[-1] - psi[0]) / 20.0
    print(f"heavy top mean precession {rate:.5f} vs k/(C r) = {mg * l / (C * r0):.5f}")
    np.testing.assert_allclose(rate, mg * l / (C * r0), rtol=0.05)


def test_area_integral_in_a_turning_frame():
    """The area integral (J ω)·γ of a heavy top described in a turning frame: the angular
    momentum about the frame's z-axis, an integral where that axis is fixed in space (the
    frame turning about it: drift ≤ `SOLVE_TOL`, as for the absolute top) and not where it
    turns (about x: the frame's turn carries the axis across L, an O(1) change)."""
    J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
    top = gravity(weight=2.0, com=(0.0, 0.1, 0.5))
    y0 = rb.State(jnp.array([0.3, -0.5, 1.2]), jnp.array([0.9, 0.1, -0.3, 0.2]) / jnp.sqrt(0.95))
    drift = {}
    for axis in (2, 0):
        rate = jnp.zeros(3).at[axis].set(0.7)
        model = rb.RelativeRigidBody(J, rb.ConstantRate(rate), top)
        drift[axis] = rel_drift(invariant("area_integral", model, solve(model, y0, 5.0)))
    assert drift[2] <= SOLVE_TOL and drift[0] > 0.1, drift


# ------------------------------------------------------------------------------------------
# 5. Newtonian field (docs/physics.md#gravity-gradient), and the three state forms agree
# ------------------------------------------------------------------------------------------

GG_T = 20.0


def _poisson_state(w, q):
    return rb.PoissonState(jnp.asarray(w), jnp.asarray(scipy_rot(q).inv().apply(E_Z)))


def test_gravity_gradient_first_integrals_poisson_form(rng):
    """docs/physics.md#torque-and-integrals, general J with products of inertia: energy ½ωᵀJω +
    ½εγᵀJγ, area (Jω)·γ and |γ| = 1 are conserved. |γ| is renormalised on output, so its
    conservation is read from `stats["norm_drift"]`, the deviation the renormalisation
    removed."""
    J = general_inertia(rng, [1.1, 1.8, 2.5])
    model = rb.PoissonRigidBody(J, gravity(eps=2.0))
    traj = solve(model, _poisson_state(rng.normal(size=3), random_quat(rng)), GG_T)
    drifts = [
        rel_drift(invariant("energy", model, traj)),
        rel_drift(invariant("area_integral", model, traj)),
        float(traj.stats["norm_drift"]),
    ]
    print(
        "Poisson gravity gradient drifts (E, area, |γ|):",
        drifts,
        traj.stats["num_accepted_steps"],
        "steps",
    )
    assert max(drifts) <= SOLVE_TOL  # ~100 × rtol, as for the heavy top
    # the torque is doing something: the kinetic energy alone is not conserved
    assert rel_drift(invariant("kinetic_energy", model, traj)) > 1e-2


def test_gravity_gradient_integrable_case(rng):
    """A = B = m C (Shinibaev et al. (2013), eq. (14); docs/physics.md#the-integrable-case):
    r, |γ|², C1 = p² + q² + ε n γ''², C2 = γp + γ'q + r(n+1)γ''."""
    A, C = 2.0, 3.0
    model = rb.PoissonRigidBody(jnp.diag(jnp.array([A, A, C])), gravity(eps=1.5))
    traj = solve(model, _poisson_state(np.array([0.7, -0.4, 1.1]), random_quat(rng)), GG_T)
    C1, C2, r, g2 = invariant("gg_integrable_integrals", model, traj)
    # independent recomputation of C1, C2 from the state (n = (1 − m)/m, m = A/C)
    n = (1 - A / C) / (A / C)
    w, g = np.asarray(traj.ys.omega), np.asarray(traj.ys.gamma)
    np.testing.assert_allclose(C1, w[:, 0] ** 2 + w[:, 1] ** 2 + 1.5 * n * g[:, 2] ** 2, atol=TIGHT)
    np.testing.assert_allclose(
        C2, g[:, 0] * w[:, 0] + g[:, 1] * w[:, 1] + w[:, 2] * (n + 1) * g[:, 2], atol=TIGHT
    )
    drifts = [rel_drift(x) for x in (r, C1, C2)] + [float(traj.stats["norm_drift"])]
    print(
        "integrable case drifts (r, C1, C2, |γ|):",
        drifts,
        traj.stats["num_accepted_steps"],
        "steps",
    )
    assert max(drifts) <= SOLVE_TOL
    assert np.ptp(g[:, 2]) > 0.05  # the axis nutates: C1, C2 are not trivially constant


@pytest.mark.parametrize("case", ["gravity_gradient", "uniform_gravity", "both"])
def test_euler_and_poisson_forms_match_quaternion_form(case, rng):
    """The same torque and initial condition in the three state forms give the same ω(t),
    attitude and γ(t) (θ kept away from the ZXZ singularity)."""
    J = general_inertia(rng, [1.2, 1.7, 2.4])
    eps, weight = {
        "gravity_gradient": (2.0, 0.0),
        "uniform_gravity": (0.0, 1.5),
        "both": (2.0, 1.5),
    }[case]
    torque = gravity(eps=eps, weight=weight, com=(0.1, -0.2, 0.5))
    angles0 = np.array([0.3, 1.3, -0.8])
    q0 = xyzw_to_wxyz(Rotation.from_euler("ZXZ", angles0).as_quat())
    w0 = np.array([0.75, -0.45, 1.2])
    T = 10.0
    quat = solve(rb.RigidBody(J, torque), rb.State(jnp.asarray(w0), jnp.asarray(q0)), T)
    euler = solve(
        rb.EulerAngleRigidBody(J, torque), rb.EulerState(jnp.asarray(w0), jnp.asarray(angles0)), T
    )
    poisson = solve(rb.PoissonRigidBody(J, torque), _poisson_state(w0, q0), T)
    theta = np.asarray(euler.ys.angles[:, 1])
    assert np.min(np.abs(np.sin(theta))) > 0.2  # away from gimbal lock
    errs = {}
    for name, traj in [("euler", euler), ("poisson", poisson)]:
        np.testing.assert_allclose(traj.ys.omega, quat.ys.omega, atol=SOLVE_TOL)
        errs[name] = float(np.max(np.abs(np.asarray(traj.ys.omega) - np.asarray(quat.ys.omega))))
    gamma_q = scipy_rot(quat.ys.quat).inv().apply(E_Z)
    np.testing.assert_allclose(poisson.ys.gamma, gamma_q, atol=SOLVE_TOL)
    assert_quat_equal(
        xyzw_to_wxyz(Rotation.from_euler("ZXZ", np.asarray(euler.ys.angles)).as_quat()),
        quat.ys.quat,
        atol=SOLVE_TOL,
    )
    print(f"state forms vs quaternion form ({case}): max |Δω|", errs)
    # the torque matters: ω changes by O(1)
    assert np.max(np.abs(np.asarray(quat.ys.omega) - w0)) > 0.1


# ------------------------------------------------------------------------------------------
# 6. Pitch libration on a circular orbit (docs/physics.md#pitch-libration)
# ------------------------------------------------------------------------------------------

ORBIT_N = 0.7


def _pitch_run(Ix, Iy, Iz, pitch0, T):
    """RelativeRigidBody in the LVLH frame under the gravity gradient, started at rest in the
    frame with a rotation `pitch0` about y1. Returns (ts, pitch angle from the quaternion)."""
    model = rb.RelativeRigidBody(
        jnp.diag(jnp.array([Ix, Iy, Iz])),
        rb.CircularOrbit(ORBIT_N),
        rb.GravityGradient.from_orbit_rate(ORBIT_N),
    )
    q0 = jnp.array([np.cos(pitch0 / 2), 0.0, np.sin(pitch0 / 2), 0.0])
    traj = solve(model, rb.State(jnp.zeros(3), q0), T, n=801)
    q = np.asarray(traj.ys.quat)
    # pure pitch stays pure pitch (the plane of the orbit is invariant for principal J)
    np.testing.assert_allclose(q[:, [1, 3]], 0.0, atol=SOLVE_TOL)
    return np.asarray(traj.ts), 2 * np.arctan2(q[:, 2], q[:, 0])


def _period_from_zero_crossings(ts, x):
    """Crossing times by cubic interpolation through the 4 samples around each sign change,
    then a least-squares line t_k = t_0 + k T/2."""
    idx = np.nonzero(np.sign(x[:-1]) * np.sign(x[1:]) < 0)[0]
    idx = idx[(idx >= 1) & (idx + 2 < len(x))]
    crossings = []
    for i in idx:
        sl = slice(i - 1, i + 3)
        roots = np.roots(np.polyfit(ts[sl] - ts[i], x[sl], 3))
        roots = roots[np.isreal(roots)].real
        roots = roots[(roots >= 0) & (roots <= ts[i + 1] - ts[i])]
        crossings.append(ts[i] + roots[0])
    if len(crossings) < 2:
        return np.nan, len(crossings)
    k = np.arange(len(crossings))
    half, _ = np.polyfit(k, crossings, 1)
    return 2 * half, len(crossings)


@pytest.mark.parametrize("pitch0", [0.01, 0.3])
def test_pitch_libration_period(pitch0):
    """docs/physics.md#pitch-libration: I_y θ'' = −3 n² (I_x − I_z) sinθ cosθ. Linear frequency
    ω0 = n sqrt(3 (I_x − I_z)/I_y); in u = 2θ this is the pendulum u'' = −ω0² sin u, whose
    exact period is 4 K(sin²(θ0)) / ω0 (K the complete elliptic integral, parameter m).

    At θ0 = 0.01 the amplitude correction (2θ0)²/16 = 2.5e-5 is below the 1e-4 asserted
    against the linear period; at θ0 = 0.3 the correction (≈ 2 %) is real and the exact
    elliptic period is matched to 1e-6 (crossing times are interpolated with cubics on a grid
    of ~100 samples per period: error ≲ 1e-8 per crossing; solver phase error ≲ 1e-8).
    """
    Ix, Iy, Iz = 2.0, 2.5, 1.0
    w0 = ORBIT_N * np.sqrt(3 * (Ix - Iz) / Iy)
    T_lin = 2 * np.pi / w0
    ts, pitch = _pitch_run(Ix, Iy, Iz, pitch0, 8 * T_lin)
    period, count = _period_from_zero_crossings(ts, pitch)
    assert count >= 14
    T_exact = 4 * ellipk(np.sin(pitch0) ** 2) / w0
    print(
        f"pitch θ0 = {pitch0}: period {period:.8f}, linear {T_lin:.8f}, exact {T_exact:.8f}, "
        f"rel. err vs exact {abs(period / T_exact - 1):.1e}"
    )
    np.testing.assert_allclose(period, T_exact, rtol=1e-6)
    if pitch0 == 0.01:
        np.testing.assert_allclose(period, T_lin, rtol=1e-4)
    else:
        assert period / T_lin - 1 > 1e-2  # the amplitude effect is resolved
    # energy conservation: the amplitude stays θ0 (samples miss the peak by ≲ (π/100)²/2)
    assert pitch0 * (1 - 1e-3) <= np.max(np.abs(pitch)) <= pitch0 * (1 + 1e-7)


def test_pitch_unstable_when_ix_below_iz():
    """I_x < I_z: θ'' ≈ λ² θ with λ = n sqrt(3 (I_z − I_x)/I_y): θ ≈ θ0 cosh(λ t) while
    small (relative error O(θ²) ≲ 1e-3 while θ ≤ 0.03), then it leaves the neighbourhood."""
    Ix, Iy, Iz, pitch0 = 1.0, 2.5, 2.0, 0.01
    lam = ORBIT_N * np.sqrt(3 * (Iz - Ix) / Iy)
    T_ref = 2 * np.pi / lam
    ts, pitch = _pitch_run(Ix, Iy, Iz, pitch0, 8 * T_ref)
    small = np.abs(pitch) <= 0.03
    small[np.argmax(~small) :] = False  # the initial small-angle stretch only
    err = np.max(np.abs(pitch[small] / (pitch0 * np.cosh(lam * ts[small])) - 1))
    print(
        f"unstable pitch: max rel. deviation from θ0 cosh(λt) while |θ| ≤ 0.03: {err:.1e}, "
        f"max |θ| {np.max(np.abs(pitch)):.2f}"
    )
    assert err <= 1e-3 and lam * ts[small][-1] > 1.5  # compared over real growth (×2.3+)
    assert np.max(np.abs(pitch)) > 1.0


def test_circular_orbit_jacobi_integral(rng):
    """General tumbling in the orbital frame (docs/physics.md#circular-orbit, general J with
    products of inertia): the frame turns uniformly and the field is stationary in it, so the
    Jacobi integral

        H = ½ ω_rᵀ J ω_r − ½ ω_eᵀ J ω_e + ½ ε γᵀ J γ,   ω_e = R_rᵀ (0, −n, 0),  γ = R_rᵀ e_z,

    (T₂ − T₀ + V of the Lagrangian in the rotating frame) is conserved. Computed here in NumPy
    from the solved quaternion with scipy; bound 1e-8 (~100 × rtol) as for the other integrals.
    """
    J = general_inertia(rng, [1.0, 1.5, 2.1])
    n = ORBIT_N
    model = rb.RelativeRigidBody(J, rb.CircularOrbit(n), rb.GravityGradient.from_orbit_rate(n))
    traj = solve(
        model,
        rb.State(jnp.asarray(0.5 * n * rng.normal(size=3)), jnp.asarray(random_quat(rng))),
        40.0,
        n=801,
    )
    Rr_inv = scipy_rot(traj.ys.quat).inv()
    w_r = np.asarray(traj.ys.omega)
    w_e, g = Rr_inv.apply([0.0, -n, 0.0]), Rr_inv.apply(E_Z)
    Tr = 0.5 * np.einsum("ni,ij,nj->n", w_r, J, w_r)
    H = (
        Tr
        - 0.5 * np.einsum("ni,ij,nj->n", w_e, J, w_e)
        + 1.5 * n**2 * np.einsum("ni,ij,nj->n", g, J, g)
    )
    drift = rel_drift(H)
    print(
        f"circular orbit Jacobi integral drift {drift:.1e} "
        f"({traj.stats['num_accepted_steps']} steps)"
    )
    assert drift <= SOLVE_TOL
    assert np.ptp(Tr) > 1e-2 * np.max(Tr)  # the relative motion is far from uniform


# ------------------------------------------------------------------------------------------
# 7. Construction errors
# ------------------------------------------------------------------------------------------

MODEL_CLASSES = [rb.RigidBody, rb.RelativeRigidBody, rb.EulerAngleRigidBody, rb.PoissonRigidBody]


@pytest.mark.parametrize("cls", MODEL_CLASSES)
def test_non_physical_or_asymmetric_inertia_is_an_error(cls):
    with pytest.raises(
        eqx.EquinoxRuntimeError,
        match="`inertia` is not physical.*docs/physics\\.md#physical-consistency",
    ):
        cls(jnp.diag(jnp.array([1.0, 1.0, 3.0])))  # 1 + 1 < 3
    with pytest.raises(eqx.EquinoxRuntimeError, match="`inertia` is not symmetric"):
        cls(jnp.array([[2.0, 0.3, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0]]))
    with pytest.raises(ValueError, match="`inertia`"):
        cls(jnp.eye(2))


def test_constructors_convert_their_fields_when_built_only():
    """The fields go through their converters when a model is built, positionally or by
    keyword: the inertia is checked, a `None` torque or frame (the defaults) is `NoTorque()`
    / `Inertial()`. Built under `eqx.filter_vmap`, each lane's 3×3 is checked and the model
    holds the batch; `eqx.tree_at` and unflattening keep a leaf as it is (a batched inertia,
    which the constructor itself refuses)."""
    J = jnp.diag(jnp.array([1.0, 2.0, 2.5]))
    torque = rb.GravityGradient(1.5)
    for cls in [rb.RigidBody, rb.EulerAngleRigidBody, rb.PoissonRigidBody]:
        assert isinstance(cls(J).torque, rb.NoTorque)
        assert cls(J, torque).torque is torque and cls(inertia=J, torque=torque).torque is torque
    frame = rb.CircularOrbit(0.3)
    rel = rb.RelativeRigidBody(J, frame, torque)
    assert rel.frame is frame and rel.torque is torque
    assert isinstance(rb.RelativeRigidBody(J).frame, rb.Inertial)
    assert isinstance(rb.RelativeRigidBody(J, torque=torque).frame, rb.Inertial)
    assert isinstance(rb.RelativeRigidBody(J, frame).torque, rb.NoTorque)
    Js = jnp.stack([J, 2.0 * J, 3.0 * J])
    with pytest.raises(ValueError, match="one 3×3 tensor"):
        rb.RigidBody(Js, torque)
    batch = eqx.filter_vmap(lambda J: rb.RigidBody(J, torque))(Js)
    np.testing.assert_array_equal(batch.inertia, Js)
    with pytest.raises(eqx.EquinoxRuntimeError, match="`inertia` is not physical"):
        eqx.filter_vmap(rb.RigidBody)(Js.at[1].set(jnp.diag(jnp.array([1.0, 1.0, 3.0]))))
    swapped = eqx.tree_at(lambda m: m.inertia, rel, Js)
    assert swapped.inertia is Js
    assert eqx.tree_equal(swapped.frame, frame) and eqx.tree_equal(swapped.torque, torque)
    leaves, treedef = jax.tree_util.tree_flatten(swapped)
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert rebuilt.inertia is Js and jax.tree_util.tree_structure(rebuilt) == treedef


def _builds(build, J):
    """True if `build(J)` succeeds, else which inertia check refused it."""
    try:
        jax.block_until_ready(build(J))
    except eqx.EquinoxRuntimeError as e:
        return [k for k in ("not symmetric", "not physical", "positive definite") if k in str(e)]
    return True


def test_eager_inertia_check_decides_as_the_traced_check():
    """A concrete inertia is checked in NumPy and skips `eqx.error_if` when it is valid
    (building the first model cost ~1 s of eager compilations, then ~0.35 s of compiling
    one jitted check). That fast
    path must accept and reject exactly what the traced checks do, with the same message,
    including at the √eps boundaries of symmetry, the triangle inequality and
    definiteness. (Every model class builds its inertia with the same `_inertia`; the test
    above runs the error paths of all four.)"""
    cls = rb.RigidBody
    eps = float(jnp.finfo(jnp.float64).eps) ** 0.5
    base = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
    asym_in, asym_out = base.copy(), base.copy()
    asym_in[0, 1] += 0.5 * eps * 4.0  # within √eps·max|J| of symmetric
    asym_out[0, 1] += 2.0 * eps * 4.0
    cases = {
        "valid": base,
        "nearly symmetric": asym_in,
        "not symmetric": asym_out,
        "on the triangle inequality": np.diag([1.0, 1.0, 2.0]),
        "just outside it": np.diag([1.0, 1.0, 2.0 + 2e-6]),
        "rod": np.diag([1.0, 1.0, 0.0]),
        "nearly a rod": np.diag([1.0, 1.0, 1e-12]),
        "NaN": np.diag([1.0, np.nan, 2.5]),
    }
    traced = eqx.filter_jit(lambda J: cls(J).inertia)  # one compilation for every case
    outcomes = {
        name: _builds(lambda J: cls(J).inertia, jnp.asarray(J)) for name, J in cases.items()
    }
    for name, J in cases.items():
        assert outcomes[name] == _builds(traced, jnp.asarray(J)), name
    assert outcomes["valid"] is True and outcomes["nearly symmetric"] is True
    assert outcomes["not symmetric"] == ["not symmetric"]
    assert outcomes["on the triangle inequality"] is True  # a flat body: physical, definite
    assert outcomes["just outside it"] == ["not physical"]
    assert outcomes["rod"] == ["positive definite"]
    assert outcomes["nearly a rod"] == ["positive definite"]
    assert outcomes["NaN"] == ["not symmetric"]


# ------------------------------------------------------------------------------------------
# 8. Fitting an inertia: `with_log_cholesky`
# ------------------------------------------------------------------------------------------


def _fit_case(cls):
    """A model of `cls` with a torque (and a frame) to keep, and a state of its form."""
    torque = rb.UniformGravity(2.0, jnp.array([0.1, -0.2, 0.5]))
    J0 = jnp.asarray(general_inertia(np.random.default_rng(3), [1.0, 2.0, 2.5]))
    w, angles = np.array([0.3, -0.5, 0.8]), np.array([0.3, 1.3, -0.8])
    q = xyzw_to_wxyz(Rotation.from_euler("ZXZ", angles).as_quat())
    if cls is rb.RelativeRigidBody:
        model = cls(J0, rb.ConstantRate(jnp.array([0.0, 0.3, 1.0])), torque)
    else:
        model = cls(J0, torque)
    y = {
        rb.EulerAngleRigidBody: rb.EulerState(jnp.asarray(w), jnp.asarray(angles)),
        rb.PoissonRigidBody: _poisson_state(w, q),
    }.get(cls, rb.State(jnp.asarray(w), jnp.asarray(q)))
    return model, y


@pytest.mark.parametrize("cls", MODEL_CLASSES)
def test_with_log_cholesky_is_the_constructed_model_without_host_callbacks(cls):
    """`with_log_cholesky(model, θ)` must be the model the constructor builds from
    `from_log_cholesky(θ)` with the model's other fields: the same leaves exactly, so the same
    vector field and gradients. Its checks are skipped because they hold by construction
    (docs/physics.md#log-cholesky-parametrisation): the constructor accepts every θ of a wide
    box (log-diagonal and off-diagonal entries in [−3, 3]). And skipping them is the point: the
    gradient program of a loss built with it holds no host callback (JAX's persistent cache can
    store it), where the constructor's run-time checks of a traced θ are callbacks."""
    model, y = _fit_case(cls)
    thetas = jnp.asarray(np.random.default_rng(5).uniform(-3.0, 3.0, size=(20, 6)))
    fields = [x for x in dir(model) if x in ("frame", "torque")]

    def built(theta):
        return cls(rb.inertia.from_log_cholesky(theta), *[getattr(model, f) for f in fields])

    for theta in thetas[:3]:  # eager: every check of the constructor runs (and passes)
        a, b = rb.with_log_cholesky(model, theta), built(theta)
        assert type(a) is cls
        assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
        for x, z in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(x, z)
    # the constructor's checks, traced once, accept the whole box
    jax.block_until_ready(eqx.filter_jit(jax.vmap(lambda th: built(th).inertia))(thetas))

    def loss(make, theta):
        f = make(theta).vector_field(jnp.asarray(0.7), y, None)
        return sum(jnp.sum(x**2) for x in jax.tree_util.tree_leaves(f))

    ours = jax.jit(jax.grad(lambda th: loss(lambda t: rb.with_log_cholesky(model, t), th)))
    ctor = jax.jit(jax.grad(lambda th: loss(built, th)))
    assert host_callbacks(ours.trace(thetas[0]).jaxpr) == []
    assert host_callbacks(ctor.trace(thetas[0]).jaxpr) != []
    g = ours(thetas[0])
    assert float(jnp.max(jnp.abs(g))) > 1e-3  # the field depends on the inertia
    # the same arithmetic, fused differently by XLA around the checks: round-off of the
    # largest component (seen 4e-16 on 0.04)
    np.testing.assert_allclose(g, ctor(thetas[0]), rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(g))))


def test_with_log_cholesky_refuses_a_concrete_non_finite_theta_and_reports_a_traced_one():
    """A concrete NaN θ is refused at once; a traced one cannot be checked without a host
    callback, so it gives a NaN inertia, which the solve reports as `nonfinite_state`."""
    model = rb.RigidBody(jnp.eye(3))
    theta = jnp.array([0.0, 0.1, 0.2, 0.0, 0.0, jnp.nan])
    with pytest.raises(ValueError, match="`theta` must be finite"):
        rb.with_log_cholesky(model, theta)
    with pytest.raises(ValueError, match="rigid-body model"):
        rb.with_log_cholesky(jnp.eye(3), theta.at[-1].set(0.0))
    bad = eqx.filter_jit(rb.with_log_cholesky)(model, theta)
    assert np.any(np.isnan(bad.inertia))
    y0 = rb.State(jnp.array([0.1, 0.2, 0.3]), jnp.array([1.0, 0.0, 0.0, 0.0]))
    traj = rb.simulate(bad, y0, jnp.linspace(0.0, 1.0, N_OUT), rtol=RTOL, atol=ATOL, throw=False)
    assert traj.result == rb.RESULTS.nonfinite_state


def test_poisson_form_rejects_attitude_torques_at_trace_time():
    y0 = rb.PoissonState(jnp.array([0.1, 0.2, 0.3]), jnp.array([0.0, 0.0, 1.0]))
    ts = jnp.linspace(0.0, 1.0, 3)
    for torque, name in [
        (rb.InertialTorque(jnp.array([1.0, 0.0, 0.0])), "InertialTorque"),
        (rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([1.0]), 0.1)), "RestoringMoment"),
    ]:
        with pytest.raises(ValueError, match=name):
            rb.simulate(rb.PoissonRigidBody(jnp.eye(3), torque), y0, ts)


def test_invariants_of_a_batched_trajectory_equal_per_trajectory():
    """Invariants map over the leading batch axes of `simulate_batch` output."""
    J = rb.inertia.from_principal(np.array([1.0, 2.0, 2.5]))
    model = rb.RigidBody(J, rb.UniformGravity(1.0, np.array([0.0, 0.0, 0.1])))
    w = np.array([[0.1, 1.0, 0.1], [0.2, -1.0, 0.3]])
    q = np.array([[1.0, 0.0, 0.0, 0.0], [0.9, 0.3, 0.0, 0.1]])
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    ts = np.linspace(0.0, 2.0, 5)
    batch = rb.simulate_batch(model, rb.State(jnp.asarray(w), jnp.asarray(q)), ts)
    E = np.asarray(rb.invariants.energy(model, batch))
    L = np.asarray(rb.invariants.angular_momentum_inertial(model, batch))
    assert E.shape == (2, 5) and L.shape == (2, 5, 3)
    for i in range(2):
        one = rb.simulate(model, rb.State(jnp.asarray(w[i]), jnp.asarray(q[i])), ts)
        np.testing.assert_allclose(E[i], rb.invariants.energy(model, one), atol=1e-12)
        np.testing.assert_allclose(
            L[i], rb.invariants.angular_momentum_inertial(model, one), atol=1e-12
        )


def test_energy_of_a_relative_model_in_a_moving_frame_is_refused():
    model = rb.RelativeRigidBody(
        np.diag([1.0, 2.0, 2.5]), rb.CircularOrbit(0.1), rb.GravityGradient.from_orbit_rate(0.1)
    )
    traj = rb.simulate(
        model, rb.State(jnp.zeros(3), jnp.array([1.0, 0, 0, 0])), np.linspace(0.0, 1.0, 3)
    )
    with pytest.raises(ValueError, match="moving frame"):
        rb.invariants.energy(model, traj)
