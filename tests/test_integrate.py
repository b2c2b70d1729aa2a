"""rbdyn_jax.simulate / simulate_batch (integrate.py) against independent references.

- an independent NumPy formulation of Euler's equations (docs/physics.md#eulers-equations) and
  the quaternion kinematics (docs/physics.md#quaternion-kinematics), integrated by scipy's
  DOP853 at rtol = atol = 1e-12, for a general J (products of inertia) under a constant body
  torque; convergence as rtol shrinks;
- `simulate_batch` equals a Python loop of `simulate`, over initial conditions, over whole
  models (`model_axes=0`) and over the inertia only (a prefix `model_axes`), also for
  models with a leaf that is no array (a plain-function restoring moment), in every
  strategy, with gradients through the forward sensitivities equal to reverse mode's;
- failure isolation in a batch (one non-finite initial state, one trajectory that runs out
  of steps) and the `throw=` switch;
- no retracing when only values change (a trace-counting torque), the first step and
  the step bounds included;
- gradients of a loss on a heavy-top-like body (restoring moment k(τ, ψ) of
  docs/physics.md#equations-of-motion with `PolynomialSinPsi`, plus a body torque) w.r.t.
  log-Cholesky inertia parameters and the restoring-moment parameters, against central finite
  differences, for two adjoints; the gradient of a batched loss equals the sum of per-trajectory
  gradients;
- input errors naming the argument.

Compilation dominates the run time, so the compiled solves are shared: one model structure
and one `max_steps` for every batch test, one gradient function per adjoint (module level).
"""

import inspect
import logging
import re

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import equations, host_callbacks
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb

# ---------------------------------------------------------------------------------------
# A general body: principal moments (2, 3, 4) (triangle inequality holds) about rotated
# axes, so J has products of inertia; a constant body torque.
J_GEN = Rotation.from_euler("ZYX", [0.4, -0.3, 0.7]).as_matrix() @ np.diag([2.0, 3.0, 4.0])
J_GEN = J_GEN @ Rotation.from_euler("ZYX", [0.4, -0.3, 0.7]).as_matrix().T
J_GEN = 0.5 * (J_GEN + J_GEN.T)
M_GEN = np.array([0.05, -0.1, 0.08])
W0 = np.array([0.4, -1.1, 0.7])
Q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
TS = np.linspace(0.0, 10.0, 11)
RTOLS = (1e-6, 1e-8, 1e-10)

# Every batch test uses this `max_steps` (a static argument: one compile for them all).
# The well-behaved members need ≤ 400 steps; the fast spinner of the max-steps test ~10⁵.
BATCH_MAX_STEPS = 1000
BATCH_TS = np.linspace(0.0, 5.0, 6)
BATCH_RTOL = 1e-10
# vmap runs every lane in lockstep, but each lane keeps its own step control: the step
# sequences are identical to the single solves (checked exactly through the step counts)
# and only XLA's batched kernels (the 3×3 solve of Euler's equations) may round
# differently. Measured ≲ 3e-14 on states of size ≲ 10; 1e-12 is rounding with margin.
BATCH_TOL = 1e-12


def gen_model():
    return rb.RigidBody(jnp.asarray(J_GEN), rb.BodyTorque(jnp.asarray(M_GEN)))


def state(omega, quat):
    return rb.State(jnp.asarray(omega), jnp.asarray(quat))


def lane(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def max_abs_diff(a, b):
    diffs = jax.tree_util.tree_map(lambda x, y: float(jnp.max(jnp.abs(x - y))), a, b)
    return max(jax.tree_util.tree_leaves(diffs))


# ---------------------------------------------------------------------------------------
# Independent reference: Euler's equations and quaternion kinematics written out in NumPy.


def numpy_rhs(J, M):
    """J ω' = J ω × ω + M (docs/physics.md#eulers-equations); q' = ½ q ⊗ (0, ω) by hand
    (docs/physics.md#quaternion-kinematics)."""

    def rhs(t, y):
        w, q = y[:3], y[3:]
        dw = np.linalg.solve(J, np.cross(J @ w, w) + M)
        qw, qx, qy, qz = q
        wx, wy, wz = w
        dq = 0.5 * np.array(
            [
                -qx * wx - qy * wy - qz * wz,
                qw * wx + qy * wz - qz * wy,
                qw * wy + qz * wx - qx * wz,
                qw * wz + qx * wy - qy * wx,
            ]
        )
        return np.concatenate([dw, dq])

    return rhs


# The tests reading a module fixture share a worker (`--dist loadgroup`, their
# `xdist_group` marks): each fixture is computed once.
@pytest.fixture(scope="module")
def scipy_ref():
    """(ω, q) at TS by DOP853 at rtol = atol = 1e-12: itself accurate to ~1e-12 here (it
    agrees with `simulate` at rtol 1e-12 to 2e-12), i.e. 100× below the finest rtol tested."""
    sol = solve_ivp(
        numpy_rhs(J_GEN, M_GEN),
        (TS[0], TS[-1]),
        np.concatenate([W0, Q0]),
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
        t_eval=TS,
    )
    assert sol.success
    return sol.y[:3].T, sol.y[3:].T


@pytest.fixture(scope="module")
def gen_solves():
    """`simulate` of the general body at each rtol of RTOLS (one compile: rtol is traced)."""
    return {
        rtol: rb.simulate(gen_model(), state(W0, Q0), TS, rtol=rtol, atol=rtol) for rtol in RTOLS
    }


def ref_error(traj, ref):
    w_ref, q_ref = ref
    return max(
        np.max(np.abs(np.asarray(traj.ys.omega) - w_ref)),
        np.max(np.abs(np.asarray(traj.ys.quat) - q_ref)),
    )


# ---------------------------------------------------------------------------------------
# 1. One trajectory.


@pytest.mark.xdist_group("integrate_single")
def test_simulate_returns_trajectory(gen_solves):
    rtol = 1e-10
    traj = gen_solves[rtol]
    n = TS.shape[0]
    assert isinstance(traj, rb.Trajectory)
    assert isinstance(traj.ys, rb.State)
    np.testing.assert_array_equal(traj.ts, TS)
    assert traj.ys.omega.shape == (n, 3) and traj.ys.quat.shape == (n, 4)
    assert traj.ys.omega.dtype == jnp.float64 and traj.ys.quat.dtype == jnp.float64
    np.testing.assert_array_equal(traj.ys.omega[0], W0)
    # The output quaternions are renormalised: unit to rounding.
    np.testing.assert_allclose(jnp.linalg.norm(traj.ys.quat, axis=-1), 1.0, rtol=0, atol=1e-14)
    stats = traj.stats
    assert set(stats) == {"num_steps", "num_accepted_steps", "num_rejected_steps", "norm_drift"}
    assert int(stats["num_steps"]) > 0
    assert int(stats["num_steps"]) == int(stats["num_accepted_steps"]) + int(
        stats["num_rejected_steps"]
    )
    # |q| drifts by the local error only: of order rtol per unit time (measured 1e-10).
    assert 0.0 <= float(stats["norm_drift"]) <= 100 * rtol
    assert traj.result == rb.RESULTS.successful


@pytest.mark.xdist_group("integrate_single")
def test_simulate_matches_scipy(gen_solves, scipy_ref):
    # Global error of an adaptive solve ≈ rtol × (error growth over 10 time units); measured
    # 8.4e-11 at rtol 1e-10. 100 × rtol is the project's bound for solver-vs-reference.
    rtol = 1e-10
    assert ref_error(gen_solves[rtol], scipy_ref) <= 100 * rtol


# ---------------------------------------------------------------------------------------
# 2. Convergence.


@pytest.mark.xdist_group("integrate_single")
def test_error_shrinks_with_rtol(gen_solves, scipy_ref):
    errors = [ref_error(gen_solves[rtol], scipy_ref) for rtol in RTOLS]
    steps = [int(gen_solves[rtol].stats["num_steps"]) for rtol in RTOLS]
    # Tsit5 (order 5) with error-per-step control: the error tracks rtol, measured
    # (1.8e-6, 8.2e-9, 8.4e-11), i.e. ×~150 per ×100 in rtol. Ask for ×10 per step of
    # rtol, and each error within 100 × rtol.
    for rtol, err in zip(RTOLS, errors, strict=True):
        assert err <= 100 * rtol, (rtol, err)
    for coarse, fine in zip(errors, errors[1:], strict=False):
        assert fine < coarse / 10, errors
    assert steps == sorted(steps) and steps[0] < steps[-1], steps


# ---------------------------------------------------------------------------------------
# 3. simulate_batch equals a loop of simulate.

B = 4
_rng = np.random.default_rng(20261121)
# Increasing spin rates: the lanes take different numbers of steps.
W0S = _rng.normal(size=(B, 3)) * np.array([[0.5], [1.0], [2.0], [3.0]])
Q0S = _rng.normal(size=(B, 4))
Q0S /= np.linalg.norm(Q0S, axis=-1, keepdims=True)
JS = np.stack([J_GEN * s for s in (1.0, 1.5, 0.7, 2.0)])
JS[2] = Rotation.from_euler("XYZ", [0.2, 0.9, -0.5]).as_matrix() @ np.diag([1.0, 1.5, 2.2])
JS[2] = JS[2] @ Rotation.from_euler("XYZ", [0.2, 0.9, -0.5]).as_matrix().T
JS[2] = 0.5 * (JS[2] + JS[2].T)


def batch(model, y0s, **kwargs):
    return rb.simulate_batch(
        model, y0s, BATCH_TS, rtol=BATCH_RTOL, atol=BATCH_RTOL, max_steps=BATCH_MAX_STEPS, **kwargs
    )


def single(model, y0):
    return rb.simulate(model, y0, BATCH_TS, rtol=BATCH_RTOL, atol=BATCH_RTOL)


@pytest.fixture(scope="module")
def clean_batch():
    return batch(gen_model(), state(W0S, Q0S))


@pytest.fixture(scope="module")
def loop_over_y0():
    return [single(gen_model(), state(W0S[i], Q0S[i])) for i in range(B)]


@pytest.fixture(scope="module")
def loop_over_models():
    torque = rb.BodyTorque(jnp.asarray(M_GEN))
    return [
        single(rb.RigidBody(jnp.asarray(JS[i]), torque), state(W0S[i], Q0S[i])) for i in range(B)
    ]


def assert_batch_equals_loop(bt, loop):
    for leaf in jax.tree_util.tree_leaves(bt):
        assert leaf.shape[0] == B, jax.tree_util.tree_map(jnp.shape, bt)
    for i, traj in enumerate(loop):
        got = lane(bt, i)
        assert max_abs_diff(got.ys, traj.ys) <= BATCH_TOL, i
        np.testing.assert_array_equal(got.ts, traj.ts)
        for key in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
            assert int(got.stats[key]) == int(traj.stats[key]), (i, key)
        np.testing.assert_allclose(
            got.stats["norm_drift"], traj.stats["norm_drift"], rtol=0, atol=BATCH_TOL
        )
        assert got.result == traj.result == rb.RESULTS.successful


@pytest.mark.xdist_group("integrate_batch")
def test_batch_over_initial_conditions_equals_loop(clean_batch, loop_over_y0):
    steps = [int(t.stats["num_steps"]) for t in loop_over_y0]
    assert len(set(steps)) == B, steps  # the lanes really do step differently
    assert_batch_equals_loop(clean_batch, loop_over_y0)


@pytest.mark.xdist_group("integrate_batch")
def test_batch_over_models_equals_loop(loop_over_models):
    torque = rb.BodyTorque(jnp.asarray(M_GEN))
    models = eqx.filter_vmap(lambda J: rb.RigidBody(J, torque))(jnp.asarray(JS))
    assert models.inertia.shape == (B, 3, 3) and models.torque.moment.shape == (B, 3)
    bt = batch(models, state(W0S, Q0S), model_axes=0)
    assert_batch_equals_loop(bt, loop_over_models)


@pytest.mark.xdist_group("integrate_batch")
def test_batch_over_inertia_only_prefix_axes(loop_over_models):
    # Only the inertia carries a batch axis; the torque is shared (axis None).
    model = eqx.tree_at(lambda m: m.inertia, gen_model(), jnp.asarray(JS))
    axes = jax.tree_util.tree_map(lambda _: None, gen_model())
    axes = eqx.tree_at(lambda m: m.inertia, axes, 0, is_leaf=lambda x: x is None)
    assert model.torque.moment.shape == (3,)
    bt = batch(model, state(W0S, Q0S), model_axes=axes)
    assert_batch_equals_loop(bt, loop_over_models)


def restoring(tau, psi):  # a plain Python function: a leaf of the model that is no array
    return 0.6 + 0.2 * jnp.sin(psi) * jnp.exp(-tau)


EPS = np.array([0.1, 0.3, 0.05, 0.2])


def function_leaf_models():
    """Per-trajectory heavy tops whose restoring moment k(τ, ψ) is `restoring`, with their
    own inertia and slow-time scale ε, and the loop of single solves they must equal."""
    models = eqx.filter_vmap(lambda J, e: rb.RigidBody(J, rb.RestoringMoment(restoring, e)))(
        jnp.asarray(JS), jnp.asarray(EPS)
    )
    loop = [
        single(
            rb.RigidBody(jnp.asarray(JS[i]), rb.RestoringMoment(restoring, EPS[i])),
            state(W0S[i], Q0S[i]),
        )
        for i in range(B)
    ]
    return models, loop


@pytest.mark.parametrize(
    "batching",
    [None, rb.Vmap(), rb.Lanes(), rb.Kernel(interpret=True)],
    ids=["default", "Vmap", "Lanes", "Kernel"],
)
def test_batched_models_share_their_non_array_leaves(batching):
    """`model_axes=0` maps a model's array leaves only: a restoring moment given as a plain
    function (a leaf that is no array) is shared by the batch, in every strategy, and the
    batch equals the loop of single solves. So does a prefix mapping the inertia alone."""
    models, loop = function_leaf_models()
    assert callable(models.torque.k) and models.torque.eps.shape == (B,)
    assert_batch_equals_loop(batch(models, state(W0S, Q0S), model_axes=0, batching=batching), loop)
    if batching is None:  # the prefix: ε shared, the inertia mapped
        shared = eqx.tree_at(lambda m: m.torque.eps, models, jnp.asarray(EPS[0]))
        axes = jax.tree_util.tree_map(lambda _: None, shared)
        axes = eqx.tree_at(lambda m: m.inertia, axes, 0, is_leaf=lambda x: x is None)
        bt = batch(shared, state(W0S, Q0S), model_axes=axes)
        ref = [
            single(
                rb.RigidBody(jnp.asarray(JS[i]), rb.RestoringMoment(restoring, EPS[0])),
                state(W0S[i], Q0S[i]),
            )
            for i in range(B)
        ]
        assert_batch_equals_loop(bt, ref)


def test_gradient_through_batched_models_with_a_function_leaf():
    """The forward sensitivities of a batch of models with a non-array leaf (`restoring`),
    through the lane solver (the rule `Kernel` shares; the forward test above runs the
    kernel on such a batch), give the gradient w.r.t. each trajectory's ε and inertia
    scale that `jax.jacfwd` through the vmapped `diffeqsolve` gives (an independent
    method: diffrax's forward mode). Both differentiate the same discrete solve,
    so they agree to round-off (measured ≤ 1.1e-11 relative, the kernel's too); 1e-9
    leaves room for the two summation orders over a few hundred steps at rtol 1e-10."""

    def loss(params, batching, adjoint=None):
        eps, scale = params
        models = eqx.filter_vmap(lambda J, e: rb.RigidBody(J, rb.RestoringMoment(restoring, e)))(
            jnp.asarray(JS) * scale[:, None, None], eps
        )
        tr = batch(models, state(W0S, Q0S), model_axes=0, batching=batching, adjoint=adjoint)
        return jnp.sum(tr.ys.omega[:, -1] ** 2) + jnp.sum(tr.ys.quat[:, -1, 1:] ** 2)

    params = (jnp.asarray(EPS), jnp.ones(B))
    got = jax.jit(jax.grad(loss), static_argnums=1)(params, rb.Lanes())
    ref = jax.jit(jax.jacfwd(loss), static_argnums=(1, 2))(params, rb.Vmap(), diffrax.ForwardMode())
    for g, r in zip(got, ref):
        assert np.min(np.abs(r)) > 1e-3  # every trajectory's ε and scale move its end state
        np.testing.assert_allclose(g, r, rtol=1e-9)


# ---------------------------------------------------------------------------------------
# 4. Failure isolation and `throw`.


# The failing trajectory is handed out at another place in the order, so the others may
# run in other lanes of the compiled loop, whose vectorised arithmetic can round the last
# bit differently by lane (seen with XLA:CPU's fusion emitters, jaxlib 0.11: 2.8e-16 on a
# step, 6e-15 relative after the batch's few hundred steps). Poisoning would differ by far
# more; step counts and codes must be identical.
LANE_ROUND_OFF = 1e-13


def assert_other_lanes_identical(bt, clean, bad):
    for i in range(B):
        if i == bad:
            continue
        assert lane(bt, i).result == rb.RESULTS.successful
        for a, b in zip(
            jax.tree_util.tree_leaves(lane(bt, i)),
            jax.tree_util.tree_leaves(lane(clean, i)),
            strict=True,
        ):
            if np.issubdtype(np.asarray(a).dtype, np.inexact):
                np.testing.assert_allclose(a, b, rtol=LANE_ROUND_OFF, atol=LANE_ROUND_OFF)
            else:
                np.testing.assert_array_equal(a, b)


@pytest.mark.xdist_group("integrate_batch")
def test_batch_isolates_nonfinite_initial_state(clean_batch):
    bad = 2
    w0s = W0S.copy()
    w0s[bad, 1] = np.nan
    bt = batch(gen_model(), state(w0s, Q0S))
    expect = np.arange(B) == bad
    np.testing.assert_array_equal(bt.result == rb.RESULTS.nonfinite_state, expect)
    np.testing.assert_array_equal(bt.result == rb.RESULTS.successful, ~expect)
    assert np.all(np.isnan(bt.ys.omega[bad])) and np.all(np.isnan(bt.ys.quat[bad]))
    assert_other_lanes_identical(bt, clean_batch, bad)


@pytest.mark.xdist_group("integrate_batch")
def test_batch_isolates_max_steps(clean_batch):
    # Lane 1 spins 200× faster: it needs ~200× the steps and runs out of BATCH_MAX_STEPS.
    fast = 1
    w0s = W0S.copy()
    w0s[fast] *= 200.0
    bt = batch(gen_model(), state(w0s, Q0S))
    expect = np.arange(B) == fast
    np.testing.assert_array_equal(bt.result == rb.RESULTS.max_steps_reached, expect)
    np.testing.assert_array_equal(bt.result == rb.RESULTS.successful, ~expect)
    assert int(bt.stats["num_steps"][fast]) == BATCH_MAX_STEPS
    assert_other_lanes_identical(bt, clean_batch, fast)


def test_batch_throw_raises():
    w0s = W0S.copy()
    w0s[0, 0] = np.inf
    with pytest.raises(eqx.EquinoxRuntimeError, match="not finite"):
        batch(gen_model(), state(w0s, Q0S), throw=True)


def test_simulate_throw_switch():
    """`simulate` and `simulate_batch` both return the outcome by default (`throw=False`),
    and raise with `throw=True`."""
    y0 = state(np.array([np.nan, 0.0, 1.0]), Q0)
    message = rb.RESULTS[rb.RESULTS.nonfinite_state]
    assert "not finite" in message
    with pytest.raises(eqx.EquinoxRuntimeError, match=re.escape(message)):
        rb.simulate(gen_model(), y0, TS, rtol=1e-8, atol=1e-8, throw=True)
    # A concrete result is read on the host; a traced one (the caller's jit) is checked by
    # `error_if` in the caller's program: both raise.
    jitted = eqx.filter_jit(
        lambda y: rb.simulate(gen_model(), y, TS, rtol=1e-8, atol=1e-8, throw=True)
    )
    with pytest.raises(eqx.EquinoxRuntimeError, match=re.escape(message)):
        jax.block_until_ready(jitted(y0))

    # … and under `jax.grad` outside `jit` (the codes traced for differentiation)
    def loss(w, fn=rb.simulate, q=Q0):
        return fn(gen_model(), state(w, q), TS, rtol=1e-8, atol=1e-8, throw=True).ys.omega.sum()

    with pytest.raises(eqx.EquinoxRuntimeError, match=re.escape(message)):
        jax.grad(loss)(jnp.asarray(y0.omega))
    with pytest.raises(eqx.EquinoxRuntimeError, match=re.escape(message)):
        jax.grad(loss)(jnp.asarray(W0S).at[1, 0].set(np.nan), rb.simulate_batch, Q0S)
    traj = rb.simulate(gen_model(), y0, TS, rtol=1e-8, atol=1e-8)
    assert traj.result == rb.RESULTS.nonfinite_state
    assert np.all(np.isnan(traj.ys.omega))
    assert inspect.signature(rb.simulate).parameters["throw"].default is False
    for name in ("throw", "adjoint"):
        assert (
            inspect.signature(rb.simulate).parameters[name].default
            is inspect.signature(rb.simulate_batch).parameters[name].default
        ), name


def test_diffrax_codes_keep_their_values():
    # The solves read a diffrax result's value as an rbdyn_jax code (`integrate._code`,
    # no table lookup): this holds only while every diffrax code keeps its value, and its
    # message, in rb.RESULTS, which is what RESULTS.promote computes.
    items = list(diffrax.RESULTS._name_to_item.values())  # equinox lists them nowhere public
    assert {"successful", "max_steps_reached", "dt_min_reached"} <= set(
        diffrax.RESULTS._name_to_item
    )
    for item in items:
        ours = rb.RESULTS.promote(item)
        assert int(rb.integrate.result_code(item)) == int(ours._value) == int(item._value)
        assert rb.RESULTS[ours] == diffrax.RESULTS[item]
    assert int(rb.integrate.result_code(rb.RESULTS.nonfinite_state)) not in {
        int(item._value) for item in items
    }


# ---------------------------------------------------------------------------------------
# 5. No recompilation when only values change.


def compiles(caplog, fn):
    """How many XLA compilations `fn()` triggers (records of `jax.log_compiles`)."""
    caplog.clear()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        fn()
    return sum("Compiling" in r.getMessage() for r in caplog.records)


def test_no_recompile_when_only_values_change(caplog):
    # Everything but the solves is computed up front, and one warm-up call at the same
    # shapes compiles the solve and the small eager checks (the inertia check, `ts`
    # monotonicity, `throw`): after it, any compilation at all would be a retrace.
    model = gen_model()
    y0, ts = state(W0, Q0), jnp.asarray(TS)
    rb.simulate(model, y0, ts, rtol=1e-8, atol=1e-8)
    calls = [  # each changes one thing: inertia and torque values, y0, ts, tolerances
        (
            rb.RigidBody(jnp.asarray(JS[2]), rb.BodyTorque(jnp.asarray(2 * M_GEN))),
            y0,
            ts,
            1e-8,
            1e-8,
        ),
        (model, state(W0S[3], Q0S[3]), ts, 1e-8, 1e-8),
        (model, y0, jnp.asarray(2 * TS + 1), 1e-8, 1e-8),
        (model, y0, ts, 1e-10, 1e-11),
    ]

    def values_change():
        for m, y, t, rtol, atol in calls:
            rb.simulate(m, y, t, rtol=rtol, atol=atol)

    assert compiles(caplog, values_change) == 0

    # The first step and the controller's step bounds are values too.
    def pid(dtmax):
        return diffrax.PIDController(rtol=1e-8, atol=1e-8, dtmin=1e-9, dtmax=dtmax)

    rb.simulate(model, y0, ts, dt0=0.01, stepsize_controller=pid(0.5))

    def bounds_change():
        for dt0, dtmax in ((0.02, 0.3), (0.005, 1.0)):
            rb.simulate(model, y0, ts, dt0=dt0, stepsize_controller=pid(dtmax))

    assert compiles(caplog, bounds_change) == 0
    # Another model structure (another torque type) is compiled anew.
    other = rb.RigidBody(jnp.asarray(J_GEN), rb.GravityGradient(jnp.asarray(0.3)))
    assert compiles(caplog, lambda: rb.simulate(other, y0, ts)) >= 1


@pytest.mark.parametrize("first", ["nan", "checked"])
def test_the_shared_field_trace_keeps_its_check_mode(first):
    """The vector field is one `jit` per solve (`integrate._field.field`), and JAX keys its
    cached traces by the inputs, not by equinox's check mode. A solve of concrete times is
    traced with its checks as NaN (cacheable), one of traced times with its checks as host
    callbacks: neither may reuse the other's trace of the field, whichever comes first.
    Here the field holds a check (the frame's `quat0` is normalised in it, and a zero one
    is an error): a callback in the checked solve's field, none in the other's."""
    frame = rb.frames.EulerAngleFrame(
        lambda t: jnp.stack([0.3 * t, 0.2 + 0.0 * t, 0.1 * t]),
        quat0=jnp.array([1.0, 0.0, 0.0, 0.0]),
    )
    model = rb.RelativeRigidBody(jnp.asarray(J_GEN), frame)
    y0, ts = state(W0, Q0), jnp.asarray(TS)
    traced = {
        "nan": lambda: jax.make_jaxpr(lambda y: rb.simulate(model, y, ts))(y0),
        "checked": lambda: jax.make_jaxpr(lambda t: rb.simulate(model, y0, t))(ts),
    }
    for mode in (first, "checked" if first == "nan" else "nan"):
        fields = [
            e.params["jaxpr"] for e in equations(traced[mode]()) if e.params.get("name") == "field"
        ]
        assert fields, "the solve's field is not the jitted `field`"
        for field in fields:
            assert (len(host_callbacks(field)) > 0) == (mode == "checked"), mode


# ---------------------------------------------------------------------------------------
# 6–7. Gradients.
#
# A heavy-top-like body (docs/physics.md#restoring-moment): fast spin about the axis of largest
# moment, tilted θ0 = 0.6 (far from the ZXZ singularity, where ψ is well defined), restoring
# coefficient k(τ, ψ) = ε_k (c0 + c1 τ) sin ψ with τ = ε_τ t, plus a small body torque; inertia
# through log-Cholesky parameters, so every perturbed J is physical.

J_TOP = np.array([[2.0, -0.1, 0.05], [-0.1, 2.1, -0.08], [0.05, -0.08, 3.5]])
M_TOP = np.array([0.01, -0.02, 0.015])
TOP_TS = np.linspace(0.0, 3.0, 4)
TOP_Q0 = Rotation.from_euler("ZXZ", [1.0, 0.6, 0.2]).as_quat(scalar_first=True)
TOP_W0S = np.array([[0.1, -0.05, 4.0], [0.3, 0.2, 2.0], [-0.2, 0.1, 8.0]])
GRAD_RTOL = 1e-10
FD_RTOL = 1e-12
FD_STEP = 1e-4
# |q| = 1 makes Σ q_i² constant: weight the components so the loss sees the attitude.
Q_WEIGHTS = np.array([1.0, 2.0, 3.0, 4.0])


def top_params():
    return {
        "theta": rb.inertia.to_log_cholesky(jnp.asarray(J_TOP)),
        "coeffs": jnp.array([1.0, 0.5]),
        "k_eps": jnp.array(0.8),
        "tau_eps": jnp.array(0.3),
    }


def top_model(p):
    k = rb.PolynomialSinPsi(p["coeffs"], p["k_eps"])
    torque = rb.RestoringMoment(k, p["tau_eps"]) + rb.BodyTorque(jnp.asarray(M_TOP))
    return rb.RigidBody(rb.inertia.from_log_cholesky(p["theta"]), torque)


def loss_of(ys):
    """Σ over output times (and batch) of |ω|² + Σ_i w_i q_i²."""
    weights = jnp.broadcast_to(jnp.asarray(Q_WEIGHTS), ys.quat.shape)
    return jnp.sum(ys.omega**2) + jnp.sum(weights * ys.quat**2)


def top_loss(p, y0, adjoint, rtol):
    traj = rb.simulate(top_model(p), y0, TOP_TS, rtol=rtol, atol=rtol, adjoint=adjoint, throw=False)
    return loss_of(traj.ys)


def top_batch_loss(p, y0s, adjoint, rtol):
    traj = rb.simulate_batch(top_model(p), y0s, TOP_TS, rtol=rtol, atol=rtol, adjoint=adjoint)
    return loss_of(traj.ys)


# Module level: each compiles once (per adjoint) and is reused by tests 6 and 7, which
# share one worker (`--dist loadgroup`).
top_grad = eqx.filter_jit(jax.grad(top_loss))
top_batch_grad = eqx.filter_jit(jax.grad(top_batch_loss))


@pytest.fixture(scope="module")
def top_fd():
    """Central differences of the loss (solves at rtol = atol = 1e-12), flattened params."""
    flat, unravel = ravel_pytree(top_params())
    y0 = state(TOP_W0S[0], TOP_Q0)
    adjoint = diffrax.RecursiveCheckpointAdjoint()
    fd = []
    for i in range(flat.size):
        e = jnp.zeros_like(flat).at[i].set(FD_STEP)
        plus = top_loss(unravel(flat + e), y0, adjoint, FD_RTOL)
        minus = top_loss(unravel(flat - e), y0, adjoint, FD_RTOL)
        fd.append(float(plus - minus) / (2 * FD_STEP))
    return np.array(fd)


@pytest.mark.parametrize(
    "adjoint",
    [diffrax.RecursiveCheckpointAdjoint(), diffrax.BacksolveAdjoint()],
    ids=["recursive_checkpoint", "backsolve"],
)
@pytest.mark.xdist_group("integrate_top_gradients")
def test_gradient_matches_finite_differences(adjoint, top_fd):
    g = top_grad(top_params(), state(TOP_W0S[0], TOP_Q0), adjoint, GRAD_RTOL)
    g = np.asarray(ravel_pytree(g)[0])
    assert np.all(np.isfinite(g)) and np.all(np.abs(g) > 1e-3)  # every parameter matters
    # FD error: truncation O(h²) ~ 1e-8 and solve noise ~ rtol_FD / h ~ 1e-8 (relative to
    # gradients of O(0.1–1)); the AD gradient is that of a 1e-10 solve (BacksolveAdjoint
    # also solves its adjoint ODE at 1e-10). Measured: ≤ 7e-7 per component (the smallest,
    # ∂/∂ε_τ ≈ −0.07), 6e-8 as a vector, for both adjoints. 1e-5 leaves margin ≥ 15×.
    np.testing.assert_allclose(g, top_fd, rtol=1e-5, atol=1e-5 * np.linalg.norm(top_fd))
    assert np.linalg.norm(g - top_fd) <= 1e-6 * np.linalg.norm(top_fd)


@pytest.mark.parametrize(
    "adjoint",
    [diffrax.RecursiveCheckpointAdjoint(), diffrax.BacksolveAdjoint()],
    ids=["recursive_checkpoint", "backsolve"],
)
@pytest.mark.xdist_group("integrate_top_gradients")
def test_batched_gradient_equals_sum_of_single_gradients(adjoint):
    p = top_params()
    y0s = state(TOP_W0S, np.broadcast_to(TOP_Q0, (TOP_W0S.shape[0], 4)))
    # Different spin rates: the lanes take different numbers of steps.
    trajs = [
        rb.simulate(top_model(p), lane(y0s, i), TOP_TS, rtol=GRAD_RTOL, atol=GRAD_RTOL)
        for i in range(TOP_W0S.shape[0])
    ]
    steps = [int(t.stats["num_steps"]) for t in trajs]
    assert len(set(steps)) == len(steps), steps
    g_batch = ravel_pytree(top_batch_grad(p, y0s, adjoint, GRAD_RTOL))[0]
    g_sum = sum(
        ravel_pytree(top_grad(p, lane(y0s, i), adjoint, GRAD_RTOL))[0]
        for i in range(TOP_W0S.shape[0])
    )
    # The same discrete solves differentiated lane by lane (for Backsolve, the same
    # adjoint solves): agreement to rounding (measured 2e-13 per component, 2e-14 as a
    # vector, for RecursiveCheckpointAdjoint); a lane whose gradient was lost
    # or mixed with another would be off by O(1).
    np.testing.assert_allclose(g_batch, g_sum, rtol=1e-8, atol=1e-8 * np.linalg.norm(g_sum))


# ---------------------------------------------------------------------------------------
# 8. Input errors.

SIMULATORS = pytest.mark.parametrize(
    "fn", [rb.simulate, rb.simulate_batch], ids=["simulate", "simulate_batch"]
)


def y0_for(fn):
    return state(W0, Q0) if fn is rb.simulate else state(W0S, Q0S)


@SIMULATORS
@pytest.mark.parametrize("ts", [[0.0, 1.0, 1.0, 2.0], [0.0, 2.0, 1.0]])
def test_non_increasing_ts(fn, ts):
    # concrete `ts` are checked before tracing (the compiled solve then holds no check) …
    with pytest.raises(ValueError, match="strictly increasing"):
        fn(gen_model(), y0_for(fn), jnp.asarray(ts))
    # … traced ones inside it (throw=False: the only check left to fire is that of `ts`)
    with pytest.raises(eqx.EquinoxRuntimeError, match="strictly increasing"):
        eqx.filter_jit(lambda t: fn(gen_model(), y0_for(fn), t, throw=False).ys)(jnp.asarray(ts))


@SIMULATORS
@pytest.mark.parametrize("ts", [[0.0], [[0.0, 1.0]]])
def test_ts_shape(fn, ts):
    with pytest.raises(ValueError, match="`ts`"):
        fn(gen_model(), y0_for(fn), jnp.asarray(ts))


@SIMULATORS
@pytest.mark.parametrize("name", ["rtol", "atol"])
@pytest.mark.parametrize("value", [0.0, -1e-8])
def test_tolerances_positive(fn, name, value):
    with pytest.raises(ValueError, match=f"`{name}`"):
        fn(gen_model(), y0_for(fn), TS, **{name: value})


@SIMULATORS
@pytest.mark.parametrize("max_steps", [0, -5, 2.5, None, 2**31])
def test_max_steps_positive_int(fn, max_steps):
    with pytest.raises(ValueError, match="`max_steps`"):
        fn(gen_model(), y0_for(fn), TS, max_steps=max_steps)


@SIMULATORS
@pytest.mark.parametrize("model", ["RigidBody", rb.BodyTorque(jnp.asarray(M_GEN)), None])
def test_not_a_model(fn, model):
    with pytest.raises(ValueError, match="`model`"):
        fn(model, y0_for(fn), TS)


def test_simulate_refuses_a_batch_of_states():
    """`simulate` takes one trajectory: a batch of states there would be one coupled system,
    its error norm over the whole batch, and is refused pointing to `simulate_batch`."""
    with pytest.raises(ValueError, match=r"one trajectory.*\(4, 3\), \(4, 4\).*simulate_batch"):
        rb.simulate(gen_model(), state(W0S, Q0S), TS)
    with pytest.raises(ValueError, match="one trajectory"):  # a scalar leaf
        rb.simulate(gen_model(), rb.State(jnp.asarray(1.0), jnp.asarray(Q0)), TS)


@SIMULATORS
def test_a_list_in_the_state_is_named(fn):
    """A list in a state's field would be taken apart into scalars: refused by name."""
    y0 = y0_for(fn)
    with pytest.raises(ValueError, match=r"`y0s?\.omega` is a list.*jnp\.asarray"):
        fn(gen_model(), rb.State(np.asarray(y0.omega).tolist(), y0.quat), TS)


@pytest.mark.parametrize(
    "batching", [None, rb.Lanes(), rb.Kernel(interpret=True)], ids=["default", "Lanes", "Kernel"]
)
def test_batch_sizes_that_disagree_are_named(batching):
    """`y0s` leaves of different leading sizes, or a model mapped by `model_axes` whose
    axis is not the batch's, are refused with the shapes, before any strategy runs."""
    with pytest.raises(ValueError, match=r"`y0s`.*\(4, 3\), \(3, 4\)"):
        rb.simulate_batch(gen_model(), state(W0S, Q0S[:3]), TS, batching=batching)
    with pytest.raises(ValueError, match="`y0s`"):
        rb.simulate_batch(gen_model(), state(W0, Q0), TS, batching=batching)  # no batch axis
    models = eqx.filter_vmap(rb.RigidBody)(jnp.asarray(JS[:3]))
    with pytest.raises(ValueError, match=r"model array of shape \(3, 3, 3\).*4 trajectories"):
        rb.simulate_batch(models, state(W0S, Q0S), TS, model_axes=0, batching=batching)
    with pytest.raises(ValueError, match="4 trajectories"):  # a model with no batch axis
        rb.simulate_batch(gen_model(), state(W0S, Q0S), TS, model_axes=0, batching=batching)


@pytest.mark.parametrize(
    "batching",
    [None, rb.Vmap(), rb.Lanes(), rb.Kernel(interpret=True)],
    ids=["default", "Vmap", "Lanes", "Kernel"],
)
def test_an_empty_batch_gives_an_empty_trajectory(batching):
    """No trajectories: every strategy returns the `Trajectory` of none, each leaf with
    its leading axis 0 and its other axes as for a batch."""
    empty = state(W0S[:0], Q0S[:0])
    got = rb.simulate_batch(gen_model(), empty, TS, batching=batching)
    full = rb.simulate_batch(gen_model(), state(W0S[:1], Q0S[:1]), TS)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(full)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(full)):
        assert a.shape == (0,) + b.shape[1:] and a.dtype == b.dtype


@pytest.mark.parametrize("batching", [rb.Vmap(), rb.Lanes()], ids=["Vmap", "Lanes"])
def test_integer_initial_states_are_the_floats_they_hold(batching):
    """Initial rates and quaternions given as integers (`[1, 0, 0, 0]`) start the solve
    from the floats they hold: the same solve, to the bit, as from float arrays (the
    kernel takes its states from the lane solver's cast, `_field.promoted`)."""
    w0 = np.array([[1, 0, 2], [0, -1, 1], [2, 1, 0], [0, 0, 1]])
    q0 = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0], [0, 0, 0, 1]])
    ints = batch(gen_model(), state(w0, q0), batching=batching)
    floats = batch(gen_model(), state(w0 * 1.0, q0 * 1.0), batching=batching)
    for a, b in zip(jax.tree_util.tree_leaves(ints), jax.tree_util.tree_leaves(floats)):
        np.testing.assert_array_equal(a, b)
    assert ints.ys.omega.dtype == jnp.float64


@pytest.mark.parametrize("batching", [None, rb.Vmap()], ids=["default", "Vmap"])
def test_float32_times_of_a_float64_solve_are_returned_in_float64(batching):
    """The solve runs in the dtype of its inputs together: float32 output times beside a
    float64 model and state give the float64 solve of the same times, `ts` included."""
    ts32, ts64 = np.asarray(TS, np.float32), np.asarray(TS, np.float32).astype(np.float64)
    one = rb.simulate(gen_model(), state(W0, Q0), ts32)
    assert one.ts.dtype == jnp.float64
    np.testing.assert_array_equal(
        one.ys.omega, rb.simulate(gen_model(), state(W0, Q0), ts64).ys.omega
    )
    many = rb.simulate_batch(gen_model(), state(W0S, Q0S), ts32, batching=batching)
    assert many.ts.dtype == jnp.float64
    np.testing.assert_array_equal(many.ts[0], ts64)


# ---------------------------------------------------------------------------------------
# 9. Initial states and models that cannot be integrated.


def test_initial_quaternion_is_normalised():
    """A non-unit y0 quaternion is the rotation of its direction: same trajectory."""
    model = gen_model()
    w0 = np.array([0.3, -0.5, 1.1])
    q_unit = Rotation.from_rotvec([0.2, 0.4, -0.1]).as_quat(scalar_first=True)
    a = rb.simulate(model, state(w0, q_unit), TS, rtol=1e-10, atol=1e-10)
    b = rb.simulate(model, state(w0, 2.5 * q_unit), TS, rtol=1e-10, atol=1e-10)
    # identical up to the rounding of q/|q| (both runs take the same steps)
    assert max_abs_diff(a.ys, b.ys) < 1e-12


def test_nonfinite_parameter_is_reported_without_running_to_max_steps():
    """A NaN torque makes the derivative non-finite from the start: its own code at once,
    not `max_steps_reached` after spending every step."""
    J = rb.inertia.from_principal(np.array([2.0, 3.0, 4.0]))
    bad = rb.RigidBody(J, rb.BodyTorque(np.array([np.nan, 0.0, 0.0])))
    traj = rb.simulate(bad, state([0.1, 0.2, 0.3], [1.0, 0, 0, 0]), TS, throw=False)
    assert traj.result == rb.RESULTS.nonfinite_state
    assert int(traj.stats["num_steps"]) < 10
    zero_q = rb.simulate(gen_model(), state([0.1, 0.2, 0.3], [0.0, 0, 0, 0]), TS, throw=False)
    assert zero_q.result == rb.RESULTS.nonfinite_state


def test_singular_inertia_is_rejected_by_the_model():
    """A rod (a zero principal moment) is physical but has no Euler dynamics."""
    with pytest.raises(eqx.EquinoxRuntimeError, match="positive definite"):
        rb.RigidBody(np.diag([1.0, 1.0, 0.0]))
