"""The lane solver, `simulate_batch(..., batching=rb.Lanes(L))`, against
`batching=rb.Vmap()`, the vmapped `diffeqsolve`.

The lane solver drives diffrax's own solver step and PID controller, so it must take the
*same* steps as `diffeqsolve` for every trajectory — checked exactly through the step
counts — and save the same values: only round-off may differ (the interpolant's weights
are formed differently; measured ≤ 5e-15 on states of size ≲ 5). Covered: a shared model
and per-trajectory models (`model_axes=0`), a relative model in a moving frame (a
time-dependent right-hand side), Tsit5 and Dopri5 (different interpolants), more
trajectories than lanes (refilling), failure isolation (a non-finite start, a trajectory out
of steps), results independent of the batch order and of the lane a trajectory ran in,
gradients in both modes (forward sensitivities) against diffrax's forward mode through
`diffeqsolve` and finite differences, a forward-over-reverse Hessian against diffrax's forward
mode, w.r.t. inertia, per-trajectory parameters, initial
states and output times (and a jvp that runs one loop, writing its saved values without
touching the whole output buffer), two XLA host devices
(shared and per-trajectory models), float32 initial states, input errors (a solver the lanes
cannot drive), and that the compiled program can enter
JAX's persistent cache (and a caller's gradient program, built with `with_log_cholesky`,
holds no host callback).
"""

import os
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import cheapest_call, equations, host_callbacks

import rbdyn_jax as rb
from rbdyn_jax import _compat as rb_compat
from rbdyn_jax.integrate._dependencies import closed_groups
from rbdyn_jax.integrate._lane_system import Plain


def batching(lanes, layout=None):
    """The lane solver with `lanes` lanes, or the vmapped `diffeqsolve` for `None`."""
    return rb.Vmap() if lanes is None else rb.Lanes(lanes, layout=layout)


def reference_adjoint(lanes):
    """The adjoint beside `batching(lanes)`: none for the lane solver (it takes none), and
    for the vmapped `diffeqsolve` diffrax's forward mode, through which the reference
    derivatives are taken by `jax.jacfwd`. Forward mode differentiates the same discrete
    solve as reverse mode (the step sizes are not differentiated), and its program
    compiles in about a third of the time of reverse mode's checkpointed loop."""
    return None if lanes is not None else diffrax.ForwardMode()


LAYOUTS = ("cpu", "array")


J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
TS = jnp.linspace(0.0, 6.0, 13)
N, LANES = 11, 4  # more trajectories than lanes, not a multiple: refills and idle lanes
RTOL = 1e-9
# Same steps (asserted exactly); the saved values differ by round-off only.
ROUND_OFF = 1e-12


def initial_states(n=N, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return rb.State(
        jnp.asarray(rng.normal(size=(n, 3))),
        jnp.asarray(q / np.linalg.norm(q, axis=1, keepdims=True)),
    )


def assert_same_solves(a, b, tol=ROUND_OFF):
    for k in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        np.testing.assert_array_equal(a.stats[k], b.stats[k], err_msg=k)
    np.testing.assert_array_equal(a.result._value, b.result._value)
    for x, y in zip(jax.tree_util.tree_leaves(a.ys), jax.tree_util.tree_leaves(b.ys)):
        np.testing.assert_allclose(x, y, rtol=0, atol=tol, equal_nan=True)
    np.testing.assert_allclose(a.stats["norm_drift"], b.stats["norm_drift"], atol=tol)


def heavy_top(weight):
    return rb.RigidBody(J, rb.UniformGravity(weight, jnp.array([0.0, 0.1, 0.5])))


CASES = {
    "torque_free_shared": lambda: (rb.RigidBody(J), None, diffrax.Tsit5()),
    "heavy_top_per_trajectory_dopri5": lambda: (
        eqx.filter_vmap(heavy_top)(jnp.linspace(0.5, 2.0, N)),
        0,
        diffrax.Dopri5(),
    ),
    # weight seen from a turning frame: the torque depends on t through the frame's attitude
    "relative_rotating_frame": lambda: (
        rb.RelativeRigidBody(
            J,
            rb.ConstantRate(jnp.array([0.0, 0.3, 1.0])),
            rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5])),
        ),
        None,
        diffrax.Tsit5(),
    ),
}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("case", CASES)
def test_same_steps_and_values_as_vmapped_diffeqsolve(case, layout):
    """From a start time that is not 0: both solvers run in the unit time s = (t − t0)/span
    and must read a time-dependent field at t0 + s·span (`integrate._field.unit_time`).
    Both layouts of the loop (the CPU's, and the accelerators' with unrolled stages and
    scattered outputs, run here on the CPU)."""
    model, axes, solver = CASES[case]()
    y0s = initial_states()
    ts = TS + 1.5
    kw = dict(model_axes=axes, solver=solver, rtol=RTOL, atol=RTOL)
    lanes = rb.simulate_batch(model, y0s, ts, batching=rb.Lanes(LANES, layout=layout), **kw)
    plain = rb.simulate_batch(model, y0s, ts, batching=rb.Vmap(), **kw)
    assert np.all(plain.result._value == 0)
    assert_same_solves(lanes, plain)
    assert lanes.ys.omega.shape == (N, len(TS), 3)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_results_do_not_depend_on_the_order_of_the_batch_or_the_lane(layout):
    """Lanes take trajectories longest-first (by |f(t0, y0)| in the tolerance scale).
    (1) A permuted batch gives the permuted results, to the bit: the bookkeeping returns
    every trajectory to its own row. (2) Replacing one trajectory by a fast spinner moves it
    to the front of the order, so every other trajectory runs in another lane and starts at
    another iteration; their results are unchanged to the bit (a lane's arithmetic is its
    own)."""
    y0s = initial_states()
    kw = dict(rtol=RTOL, atol=RTOL, batching=rb.Lanes(LANES, layout=layout))
    a = rb.simulate_batch(rb.RigidBody(J), y0s, TS, **kw)
    perm = np.random.default_rng(3).permutation(N)
    b = rb.simulate_batch(rb.RigidBody(J), jax.tree_util.tree_map(lambda x: x[perm], y0s), TS, **kw)
    for x, y in zip(
        jax.tree_util.tree_leaves((a.ys, a.stats)), jax.tree_util.tree_leaves((b.ys, b.stats))
    ):
        np.testing.assert_array_equal(np.asarray(x)[perm], y)
    assert np.argmax(a.stats["num_steps"]) != 5  # it moves up the order: the rest move down
    spinner = rb.State(y0s.omega.at[5].set(jnp.array([0.3, 6.0, 1.0])), y0s.quat)
    c = rb.simulate_batch(rb.RigidBody(J), spinner, TS, **kw)
    assert c.stats["num_steps"][5] > np.max(np.delete(np.asarray(a.stats["num_steps"]), 5))
    keep = np.arange(N) != 5
    for x, y in zip(
        jax.tree_util.tree_leaves((a.ys, a.stats)), jax.tree_util.tree_leaves((c.ys, c.stats))
    ):
        np.testing.assert_array_equal(np.asarray(x)[keep], np.asarray(y)[keep])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_clip_floor_is_diffrax_clip_floor(dtype):
    """The lane solver's end-of-interval clip (a step ending within 100 floats of t1 ends
    at t1) uses diffeqsolve's threshold for the unit time's t1 = 1: 1 moved down by 100
    calls of equinox's `prevbefore`. It must equal that loop and the closed form 1 − 100·ε⁻
    (ε⁻ the spacing of the floats just below 1), in the solve's dtype."""
    from equinox.internal import prevbefore

    from rbdyn_jax.integrate._lane_step import clip_floor

    want = jnp.ones((), dtype)
    for _ in range(100):
        want = prevbefore(want)
    got = clip_floor(np.dtype(dtype))
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, np.asarray(want))
    np.testing.assert_array_equal(got, dtype(1) - dtype(100) * np.finfo(dtype).epsneg)
    assert got < 1


def test_vmap_over_the_lane_solver_gives_each_member_its_own_solve():
    """`jax.vmap` over a lane solve (here over the weight of a heavy top that the whole
    batch shares) must give each member exactly its own solve: the loop's state carries are
    tied to the inputs from the start (so that JAX's batching fixpoint converges in one
    pass), and every carry that depends on the mapped weight must be batched, while the
    members' step counts differ."""
    weights = jnp.array([0.5, 3.0])
    y0s = initial_states()

    def solve(w):
        return rb.simulate_batch(
            heavy_top(w), y0s, TS, rtol=RTOL, atol=RTOL, batching=rb.Lanes(LANES)
        )

    both = jax.vmap(solve)(weights)
    alone = [solve(w) for w in weights]
    assert np.any(alone[0].stats["num_steps"] != alone[1].stats["num_steps"])
    for i, one in enumerate(alone):
        assert_same_solves(jax.tree_util.tree_map(lambda x, i=i: x[i], both), one)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_failures_stay_in_their_lane(layout):
    """A NaN start is `nonfinite_state`, a fast spinner runs out of steps; the lanes they
    shared go on with other trajectories, which equal the plain solve."""
    y0s = initial_states()
    omega = y0s.omega.at[2].set(jnp.nan).at[7].set(jnp.array([0.0, 400.0, 1.0]))
    y0s = rb.State(omega, y0s.quat)
    kw = dict(rtol=RTOL, atol=RTOL, max_steps=300)
    lanes = rb.simulate_batch(
        rb.RigidBody(J), y0s, TS, batching=rb.Lanes(LANES, layout=layout), **kw
    )
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Vmap(), **kw)
    codes = np.asarray(lanes.result._value)
    assert codes[2] == rb.RESULTS.nonfinite_state._value
    assert codes[7] == rb.RESULTS.max_steps_reached._value
    assert np.sum(codes == 0) == N - 2
    assert_same_solves(lanes, plain)


def test_failed_trajectories_leave_the_gradient_of_the_others_alone():
    """A NaN start and a trajectory out of steps (its unsaved rows stay inf), masked out of
    the loss by their codes: reverse mode through the lanes must give the others'
    gradient, finite, equal to diffrax's forward mode through the vmapped `diffeqsolve`
    (its symmetric part, w.r.t. a raw J), not inf · 0 = NaN in every shared parameter."""
    y0s = initial_states()
    omega = y0s.omega.at[2].set(jnp.nan).at[7].set(jnp.array([0.0, 400.0, 1.0]))
    y0s = rb.State(omega, y0s.quat)

    def loss(J, lanes):
        tr = rb.simulate_batch(
            rb.RigidBody(J),
            y0s,
            TS,
            rtol=RTOL,
            atol=RTOL,
            max_steps=300,
            batching=batching(lanes),
            adjoint=reference_adjoint(lanes),
        )
        ok = (tr.result == rb.RESULTS.successful)[:, None, None]
        return jnp.sum(jnp.sin(jnp.where(ok, tr.ys.omega, 0.0))) + jnp.sum(
            jnp.where(ok, tr.ys.quat, 0.0)[..., 1:] ** 2
        )

    lanes = jax.jit(jax.grad(loss), static_argnums=1)(J, LANES)
    plain = jax.jit(jax.jacfwd(loss), static_argnums=1)(J, None)
    assert np.all(np.isfinite(plain))
    sym = 0.5 * (plain + plain.T)
    np.testing.assert_allclose(lanes, sym, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(sym))))


def test_gradients_in_both_modes_match_diffrax_forward_mode_and_finite_differences():
    """d/dθ of a batched loss, θ the log-Cholesky inertia parameters: `jax.jacfwd` and
    `jax.grad` through the lane solver (its forward sensitivities) vs `jax.jacfwd` through
    the vmapped `diffeqsolve` (diffrax's forward mode) and vs central differences. The
    sensitivities are integrated by the same Runge–Kutta steps as the states, which makes
    them the exact derivative of the discrete solve (Runge–Kutta methods commute with
    linearisation), and neither path differentiates the step sizes: the three agree to
    round-off. The finite
    differences (h = 1e-6 on O(1) θ, solves at rtol 1e-11) carry O(h²) + rtol/h ≈ 1e-5
    relative error. The loss reads the attitude too, whose sensitivities take another
    path (quaternion kinematics). The lanes' loss builds its model with `with_log_cholesky`,
    whose gradient program must hold no host callback (so that JAX's persistent cache can
    store it), where the constructor's run-time inertia checks hold some."""
    y0s = initial_states(6, seed=1)
    ts = jnp.linspace(0.0, 3.0, 7)
    # data from a different body (not a multiple of J: torque-free ω(t) is scale-free)
    J_data = J + jnp.diag(jnp.array([0.1, 0.0, 0.0]))
    obs = rb.simulate_batch(rb.RigidBody(J_data), y0s, ts, rtol=1e-11, atol=1e-11).ys
    theta0 = rb.inertia.to_log_cholesky(J)

    def loss(theta, lanes):
        # the lanes take the model as `identify.fit` builds it (`with_log_cholesky`: no
        # inertia check, physical by construction); the reference path, the constructor
        if lanes is None:
            model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
        else:
            model = rb.with_log_cholesky(rb.RigidBody(J), theta)
        tr = rb.simulate_batch(
            model,
            y0s,
            ts,
            rtol=1e-11,
            atol=1e-11,
            batching=batching(lanes),
            adjoint=reference_adjoint(lanes),
        )
        return jnp.sum((tr.ys.omega - obs.omega) ** 2) + jnp.sum((tr.ys.quat - obs.quat) ** 2)

    fwd = jax.jit(jax.jacfwd(lambda th: loss(th, LANES)))(theta0)
    grad_lanes = jax.jit(jax.grad(lambda th: loss(th, LANES)))
    rev_lanes = grad_lanes(theta0)
    plain = jax.jit(jax.jacfwd(lambda th: loss(th, None)))
    # The caller's whole gradient program holds no host callback, so JAX's persistent
    # cache can store it; the constructor's run-time inertia checks are callbacks.
    assert host_callbacks(grad_lanes.trace(theta0).jaxpr) == []
    assert host_callbacks(plain.trace(theta0).jaxpr) != []
    plain = plain(theta0)
    assert float(jnp.max(jnp.abs(plain))) > 1e-2  # a real gradient, not round-off
    for g in (fwd, rev_lanes):
        np.testing.assert_allclose(g, plain, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(plain))))
    f = jax.jit(lambda th: loss(th, LANES))
    h = 1e-6
    fd = np.array(
        [
            (f(theta0.at[i].add(h)) - f(theta0.at[i].add(-h))) / (2 * h)
            for i in range(theta0.shape[0])
        ]
    )
    np.testing.assert_allclose(fwd, fd, rtol=1e-4, atol=1e-5 * np.max(np.abs(fd)))


COUPLED = {  # model, and the state leaves each leaf's sensitivities need
    "torque_free": (lambda: rb.RigidBody(J), [(0,), (0, 1)]),
    "body_torque": (
        lambda: rb.RigidBody(J, rb.BodyTorque(jnp.array([0.1, -0.2, 0.3]))),
        [(0,), (0, 1)],
    ),
    "heavy_top": (lambda: heavy_top(1.0), [(0, 1), (0, 1)]),
    "inertial_torque": (
        lambda: rb.RigidBody(J, rb.InertialTorque(jnp.array([0.1, 0, 0.2]))),
        [(0, 1), (0, 1)],
    ),
    "relative_rotating_frame": (
        lambda: rb.RelativeRigidBody(J, rb.ConstantRate(jnp.array([0.0, 0.3, 1.0]))),
        [(0, 1), (0, 1)],
    ),
}


@pytest.mark.parametrize("case", COUPLED)
def test_closed_groups_follow_the_jacobian(case):
    """`_closed_groups` reads which state leaves each leaf's rate depends on from the jaxpr
    of the field's JVP. Checked against the Jacobian of the field itself (`jax.jacfwd`, at
    a generic state): where ∂ω̇/∂q is not zero (a torque fixed in space, gravity, a turning
    frame) ω's group holds q; for a free body or a torque fixed in the body, ∂ω̇/∂q is
    exactly zero and ω's group is ω alone. q̇ = ½ q ⊗ ω reads both."""
    make, expected = COUPLED[case]
    model = make()
    y = rb.State(jnp.array([0.3, -1.1, 0.7]), jnp.array([0.8, 0.1, -0.3, 0.5]) / jnp.sqrt(0.99))
    jac = jax.jacfwd(lambda y: model.vector_field(0.4, y, None))(y)
    coupled = float(jnp.max(jnp.abs(jac.omega.quat)))
    assert (coupled > 1e-3) == (expected[0] == (0, 1)), coupled
    assert coupled == 0.0 or expected[0] == (0, 1)
    assert closed_groups(model, 0.4, y) == expected


def _read(tr, reads):
    """The loss on what `reads` names: ω, the attitude, or both."""
    out = 0.0
    if reads != "quat":
        out = out + jnp.sum(jnp.sin(tr.ys.omega))
    if reads in ("quat", "both"):
        out = out + jnp.sum(tr.ys.quat[..., 1:] ** 2)
    return out


SENSITIVITY_TS = jnp.linspace(0.0, 3.0, 7)


def _sensitivity_solve(theta, heavy, lanes):
    model = rb.with_log_cholesky(heavy_top(1.0) if heavy else rb.RigidBody(J), theta)
    y0s = initial_states(6, seed=2)
    return rb.simulate_batch(
        model,
        y0s,
        SENSITIVITY_TS,
        rtol=1e-11,
        atol=1e-11,
        batching=batching(lanes),
        adjoint=reference_adjoint(lanes),
    )


@pytest.fixture(scope="module")
def free_body_forward_mode():
    """Diffrax's forward mode through the vmapped `diffeqsolve` of the free body's losses
    on ω and on the attitude, in one program (the references of the cases reading them)."""
    theta0 = rb.inertia.to_log_cholesky(J)
    parts = jax.jit(
        jax.jacfwd(
            lambda th: jnp.stack(
                [_read(_sensitivity_solve(th, False, None), r) for r in ("omega", "quat")]
            )
        )
    )(theta0)
    return {"omega": parts[0], "quat": parts[1], "both": parts[0] + parts[1]}


@pytest.mark.parametrize("reads", ["omega", "quat", "both", "omega_heavy_top"])
@pytest.mark.xdist_group("lanes_free_body_forward_mode")  # one worker: the fixture runs once
def test_a_loss_integrates_the_sensitivities_it_reads(reads, request):
    """A loss on a torque-free body's ω alone integrates ω's sensitivities alone (18 of
    the 42 columns of six inertia parameters): JAX's dead-code elimination, which `jit`
    runs before lowering, leaves the caller's program with the sensitivities' solve of ω's
    group (`_cheapest`). A loss that reads the attitude runs the whole state's; so does a
    heavy top's loss on ω (gravity couples ω̇ to q). Every gradient matches diffrax's
    forward mode through the vmapped `diffeqsolve` to round-off (the same steps, tolerance as in the
    test above)."""
    heavy = reads == "omega_heavy_top"
    theta0 = rb.inertia.to_log_cholesky(J)
    read = "omega" if heavy else reads

    grad = jax.jit(jax.grad(lambda th: _read(_sensitivity_solve(th, heavy, LANES), read)))
    call = cheapest_call(grad.trace(theta0).jaxpr)
    carried = {k[1] for k in call.params["keys"][call.params["chosen"]] if k[0] == "S"}
    assert carried == ({0} if reads == "omega" else {0, 1})
    assert len(call.params["programs"]) == (1 if heavy else 2)
    if heavy:
        ref = jax.jit(jax.jacfwd(lambda th: _read(_sensitivity_solve(th, True, None), read)))(
            theta0
        )
    else:
        ref = request.getfixturevalue("free_body_forward_mode")[reads]
    assert float(jnp.max(jnp.abs(ref))) > 1e-2
    np.testing.assert_allclose(
        grad(theta0), ref, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(ref)))
    )


def test_hessian_forward_over_reverse_through_the_lanes():
    """Second derivatives: `jacfwd(jacrev)` through the lane solver differentiates its
    sensitivities' rule again (the rule is a `custom_jvp` of an ordinary loop), where the
    default path's checkpointed reverse mode refuses forward mode. Against `jacfwd(jacfwd)`
    through the vmapped `diffeqsolve` with `diffrax.ForwardMode` (diffrax's own forward
    mode through its loop): the same discrete solve, step sizes not differentiated, so
    round-off only (seen 3e-15 relative; bound 1e-10). A heavy top and a loss on the
    attitude, so that the second derivatives couple rates, attitude and inertia."""
    y0s = initial_states(4, seed=2)
    ts = jnp.linspace(0.0, 2.0, 5)
    theta0 = rb.inertia.to_log_cholesky(J) + 0.05

    def loss(theta, lanes, adjoint=diffrax.RecursiveCheckpointAdjoint()):
        model = rb.RigidBody(
            rb.inertia.from_log_cholesky(theta), rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5]))
        )
        tr = rb.simulate_batch(
            model,
            y0s,
            ts,
            rtol=RTOL,
            atol=RTOL,
            batching=batching(lanes),
            **({} if lanes else {"adjoint": adjoint}),
        )
        return jnp.sum(tr.ys.omega**2) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    H = jax.jit(jax.jacfwd(jax.jacrev(lambda th: loss(th, LANES))))(theta0)
    H_plain = jax.jit(jax.jacfwd(jax.jacfwd(lambda th: loss(th, None, diffrax.ForwardMode()))))(
        theta0
    )
    scale = float(jnp.max(jnp.abs(H_plain)))
    assert scale > 1.0  # a real Hessian, not round-off
    np.testing.assert_allclose(H, H_plain, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(H, H.T, rtol=0, atol=1e-10 * scale)


def test_gradients_for_per_trajectory_models_initial_states_and_times():
    """Reverse mode through the lane solver, per-trajectory heavy tops (`model_axes=0`),
    w.r.t. each top's weight, the initial rates and attitudes (unnormalised: the solve
    normalises them, and so must the derivative), against diffrax's forward mode through
    the vmapped `diffeqsolve`: round-off, as above. W.r.t. the output times the two differ
    by design: the lane solver gives f(tᵢ, y(tᵢ)) and, for t0, the variational solution of
    −f(t0, y0); `diffeqsolve` differentiates its interpolant. Both approximate the exact derivative
    within the local error of a step at rtol 1e-11, ~1e-8 relative: the times are checked
    to 1e-6, and t0's against central differences (h = 1e-5: O(h²) + rtol/h ≈ 1e-6)."""
    y0s = initial_states()
    q0 = 1.3 * y0s.quat  # not unit: the solve normalises
    weights = jnp.linspace(0.5, 2.0, N)
    ts = jnp.linspace(0.0, 3.0, 7)
    tol = 1e-11

    def loss(w, omega, quat, ts, lanes):
        tops = eqx.filter_vmap(heavy_top)(w)
        tr = rb.simulate_batch(
            tops,
            rb.State(omega, quat),
            ts,
            rtol=tol,
            atol=tol,
            model_axes=0,
            batching=batching(lanes),
            adjoint=reference_adjoint(lanes),
        )
        return jnp.sum(jnp.sin(tr.ys.omega)) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    args = (weights, y0s.omega, q0, ts)
    lanes = jax.jit(jax.grad(lambda *a: loss(*a, LANES), argnums=(0, 1, 2, 3)))(*args)
    plain = jax.jit(jax.jacfwd(lambda *a: loss(*a, None), argnums=(0, 1, 2, 3)))(*args)
    for name, a, b in zip(("weight", "omega0", "quat0"), lanes[:3], plain[:3]):
        scale = float(jnp.max(jnp.abs(b)))
        assert scale > 1e-2, name
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * scale, err_msg=name)
    np.testing.assert_allclose(
        lanes[3], plain[3], rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(plain[3])))
    )
    f = jax.jit(lambda t0: loss(*args[:3], ts.at[0].set(t0), LANES))
    h = 1e-5
    fd = (f(ts[0] + h) - f(ts[0] - h)) / (2 * h)
    np.testing.assert_allclose(lanes[3][0], fd, rtol=1e-5)


def test_inertia_gradients_are_taken_on_symmetric_tensors():
    """The lane solver differentiates an inertia along the six symmetric directions (its
    sensitivities: six columns, not nine), and counts a tangent by its symmetric part. The
    gradient w.r.t. a raw J is then the symmetric part of the derivative through
    `diffeqsolve` (diffrax's forward mode), (g + gᵀ)/2, whose two off-diagonal halves each
    see one element; along any symmetric direction the two agree. Shared and
    per-trajectory inertias; the torque (a gravity gradient, ε γ × J γ) reads the inertia
    too."""
    y0s = initial_states()
    scale = np.random.default_rng(3).uniform(0.9, 1.1, size=(N, 3))
    Js = jnp.asarray(np.sqrt(scale)[:, :, None] * np.asarray(J)[None] * np.sqrt(scale)[:, None, :])
    orbit = rb.GravityGradient(1.0)

    def loss(J, lanes, axes):
        body = (
            eqx.filter_vmap(lambda J: rb.RigidBody(J, orbit))(J)
            if axes == 0
            else rb.RigidBody(J, orbit)
        )
        tr = rb.simulate_batch(
            body,
            y0s,
            TS,
            rtol=RTOL,
            atol=RTOL,
            model_axes=axes,
            batching=batching(lanes),
            adjoint=reference_adjoint(lanes),
        )
        return jnp.sum(jnp.sin(tr.ys.omega)) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    # jitted whole: the callers' programs, not op-by-op compiles of the model's construction
    plain_jac = jax.jit(jax.jacfwd(loss), static_argnums=(1, 2))
    lanes_grad = jax.jit(jax.grad(loss), static_argnums=(1, 2))
    for J_, axes in ((J, None), (Js, 0)):
        plain = plain_jac(J_, None, axes)
        lanes = lanes_grad(J_, LANES, axes)
        sym = 0.5 * (plain + jnp.swapaxes(plain, -1, -2))
        assert float(jnp.max(jnp.abs(plain - sym))) > 1e-2  # plain's halves differ
        np.testing.assert_allclose(lanes, sym, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(sym))))


class PrincipalBody(rb.AbstractRigidBody):
    """A user's model whose `inertia` leaf is its three principal moments, shape (3,)."""

    inertia: jax.Array
    torque: rb.AbstractTorque = rb.NoTorque()
    normalize = rb.RigidBody.normalize  # a unit quaternion, as the rigid body's

    def kinematics(self, t, y):
        raise NotImplementedError  # no torque reads it

    def vector_field(self, t, y, args):
        return rb.State(
            rb.dynamics.euler_rhs(jnp.diag(self.inertia), y.omega, jnp.zeros(3)),
            rb.rotation.quat_derivative(y.quat, y.omega),
        )


def test_an_inertia_that_is_not_a_tensor_takes_ordinary_columns():
    """Only a 3×3 `inertia` is differentiated along symmetric directions; principal moments
    (shape (3,)) take one column each, and equal diffrax's forward mode through
    `diffeqsolve`."""
    y0s = initial_states()

    def loss(moments, lanes):
        tr = rb.simulate_batch(
            PrincipalBody(moments),
            y0s,
            TS,
            rtol=RTOL,
            atol=RTOL,
            batching=batching(lanes),
            adjoint=reference_adjoint(lanes),
        )
        return jnp.sum(jnp.sin(tr.ys.omega))

    moments = jnp.array([2.0, 3.0, 4.0])
    plain = jax.jit(jax.jacfwd(loss), static_argnums=1)(moments, None)
    lanes = jax.jit(jax.grad(loss), static_argnums=1)(moments, LANES)
    np.testing.assert_allclose(lanes, plain, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(plain))))


_COMPILES = []  # set to a list to record the XLA compilations (a listener stays registered)
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **_: (
        _COMPILES.append(event) if event == "/jax/core/compile/backend_compile_duration" else None
    )
)


def test_eager_gradients_and_vmaps_reuse_their_compiled_solve():
    """`jax.grad` and `jax.vmap` called eagerly (no jit of the caller's) around a lane solve
    compile it once: later calls compile nothing. (A lane solve traced in place inside the
    caller's transformation instead of as a nested jit recompiled its loop at every call,
    2.3 s per eager gradient against 0.014 s, measured.)"""
    y0s = initial_states()

    def loss(J):
        return jnp.sum(
            rb.simulate_batch(
                rb.RigidBody(J), y0s, TS, rtol=RTOL, atol=RTOL, batching=rb.Lanes(LANES)
            ).ys.omega
            ** 2
        )

    def omegas(w):
        return rb.simulate_batch(
            heavy_top(w), y0s, TS, rtol=RTOL, atol=RTOL, batching=rb.Lanes(LANES)
        ).ys.omega

    for f, x in ((jax.grad(loss), J), (jax.vmap(omegas), jnp.array([0.5, 1.0]))):
        for _ in range(2):
            jax.block_until_ready(f(x))
        other = jax.block_until_ready(x + 0.01)  # new values, not a new program
        _COMPILES.clear()
        jax.block_until_ready(f(other))
        assert _COMPILES == [], f"{len(_COMPILES)} compilations on a repeated call"


def test_a_jvp_runs_one_loop_with_the_sensitivities_and_the_same_steps():
    """The tangents never enter the loop: a `jax.jvp` holds one lane loop, which carries
    the states with their sensitivities (its saved values: a plain `scatter` promising
    unique indices, not JAX's scatter JVP, a masked scatter-add over the whole output at
    every iteration, measured quadratic in the batch size), and it takes the steps of the
    forward solve, whose values it returns."""
    y0s = initial_states()

    def solve(J):
        return rb.simulate_batch(
            rb.RigidBody(J), y0s, TS, rtol=RTOL, atol=RTOL, batching=rb.Lanes(LANES)
        )

    jaxpr = jax.make_jaxpr(lambda J, dJ: jax.jvp(solve, (J,), (dJ,)))(J, jnp.eye(3))
    # The sensitivities' solves: one program per closed group of the state's leaves, of
    # which the caller's program runs one (`_cheapest`); each is one loop.
    call = cheapest_call(jaxpr, eliminate=False)
    assert len(call.params["programs"]) == 2  # ω alone, the whole state
    for program in call.params["programs"]:
        loops = [
            e
            for e in equations(program.jaxpr)
            if e.primitive.name == "while"
            and any(
                s.primitive.name.startswith("scatter")
                for s in equations(e.params["body_jaxpr"].jaxpr)
            )
        ]
        assert len(loops) == 1
    floats = [
        e
        for e in equations(jaxpr.jaxpr)
        if e.primitive.name.startswith("scatter")
        and jnp.issubdtype(e.invars[0].aval.dtype, jnp.floating)
    ]
    assert floats
    for e in floats:
        assert e.primitive.name == "scatter", e.primitive.name
        assert e.params["unique_indices"], e
    tr, dtr = jax.jit(lambda J, dJ: jax.jvp(solve, (J,), (dJ,)))(J, jnp.eye(3))
    assert_same_solves(tr, solve(J))
    assert float(jnp.max(jnp.abs(dtr.ys.omega))) > 1e-3


# Stage sums in another order, with the tableaus' coefficients up to ~20 in size (Dopri8,
# Tsit5) cancelling: measured ≤ 3e-15 on O(1) states.
ROUND_OFF_STEP = 2e-14
ERK_SOLVERS = [
    diffrax.Tsit5(),
    diffrax.Dopri5(),
    diffrax.Dopri8(),
    diffrax.Bosh3(),
    diffrax.Ralston(),
    diffrax.Midpoint(),
    diffrax.Heun(),
]


@pytest.mark.parametrize("solver", ERK_SOLVERS, ids=lambda s: type(s).__name__)
def test_unrolled_step_is_diffrax_step(solver):
    """The array layout's step (`_lane_step.unrolled_step`: the stages unrolled from the
    solver's Butcher tableau) against diffrax's own `solver.step` on a time-dependent field
    (a relative body in a turning frame, whose torque reads t at each stage's cᵢ) over a
    lane axis: the same solution, error estimate, dense output (every key, the stages'
    increments included) and FSAL stage, to round-off (the stages are summed in another
    order, `ROUND_OFF_STEP`)."""
    from rbdyn_jax.integrate._lane_step import unrolled_step
    from rbdyn_jax.integrate._lane_system import LaneField

    model = rb.RelativeRigidBody(
        J,
        rb.ConstantRate(jnp.array([0.0, 0.3, 1.0])),
        rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5])),
    )
    y = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -1), initial_states(5))
    ok = jnp.ones(5, bool)
    field = LaneField(Plain(model), False, jnp.asarray(0.7), jnp.asarray(2.0))
    term = rb_compat.wrapped_term(diffrax.ODETerm(field))
    t0, t1 = jnp.full(5, 0.1), jnp.linspace(0.2, 0.4, 5)
    fsal = solver.tableau.fsal
    f0 = field(t0, y, ok) if fsal else None
    with jax.numpy_rank_promotion("allow"):
        want = solver.step(term, t0, t1, y, ok, (jnp.array(False), f0) if fsal else None, False)
        got = unrolled_step(solver, term, t0, t1, y, ok, f0)
    y1, err, dense, state, result = want
    assert result == diffrax.RESULTS.successful
    assert jax.tree_util.tree_structure(got[2]) == jax.tree_util.tree_structure(dense)
    pairs = [(got[0], y1), (got[1], err), (got[2], dense)]
    if fsal:
        pairs.append((got[3], state[1]))
    else:
        assert got[3] is None
    for a, b in pairs:
        for x, z in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
            np.testing.assert_allclose(x, z, rtol=0, atol=ROUND_OFF_STEP)
    assert float(jnp.max(jnp.abs(err.omega))) > 1e-8  # a real error estimate


def test_the_array_layout_differentiates_as_the_cpu_layout():
    """Forward sensitivities run through the same loop: `jax.grad` and `jax.jacfwd` of a
    batched loss (w.r.t. the log-Cholesky inertia) through the array layout equal the CPU
    layout's to round-off, with refills (more trajectories than lanes)."""
    y0s = initial_states()
    theta0 = rb.inertia.to_log_cholesky(J)

    def loss(theta, layout):
        tr = rb.simulate_batch(
            rb.with_log_cholesky(rb.RigidBody(J), theta),
            y0s,
            TS,
            rtol=RTOL,
            atol=RTOL,
            batching=rb.Lanes(LANES, layout=layout),
        )
        return jnp.sum(jnp.sin(tr.ys.omega)) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    grad = jax.jit(jax.grad(loss), static_argnums=1)
    ref = grad(theta0, "cpu")
    assert float(jnp.max(jnp.abs(ref))) > 1e-2
    for g in (grad(theta0, "array"), jax.jit(jax.jacfwd(loss), static_argnums=1)(theta0, "array")):
        np.testing.assert_allclose(g, ref, rtol=1e-10, atol=1e-12)


def test_layouts_by_platform_and_lanes_by_memory():
    """The default layout follows the device's platform; on an accelerator every
    trajectory of a device's share gets a lane while their working set fits the memory
    budget (`default_lanes`), and a bad layout is refused."""
    from rbdyn_jax.integrate._batching import (
        LANE_COPIES,
        MAX_LANES_ARRAY,
        MEMORY_SHARE,
        MIN_LANES_ARRAY,
        PER_LANE_ARRAY,
        default_lanes,
        default_layout,
        lane_bytes,
    )

    assert default_layout("cpu") == "cpu"
    assert default_layout("gpu") == default_layout("tpu") == "array"
    y0s = initial_states(4)
    assert lane_bytes(y0s) == 7 * 8
    tops = eqx.filter_vmap(heavy_top)(jnp.ones(4))
    assert lane_bytes(y0s, tops) == 7 * 8 + (9 + 1 + 3) * 8  # J, weight, centre of mass
    per_lane, memory = 56, 80 << 30
    for n in (1, 1000, MIN_LANES_ARRAY):  # a small batch: a lane per trajectory
        assert default_lanes(n, 1, "gpu", per_lane, memory) == n
    assert default_lanes(1000, 2, "gpu", per_lane, memory) == 500
    assert default_lanes(10**5, 1, "gpu", per_lane, memory) == -(-(10**5) // PER_LANE_ARRAY)
    assert default_lanes(4 * MIN_LANES_ARRAY, 1, "gpu", per_lane, memory) == -(
        -4 * MIN_LANES_ARRAY // PER_LANE_ARRAY
    )
    assert default_lanes(2 * MIN_LANES_ARRAY, 1, "gpu", per_lane, memory) == MIN_LANES_ARRAY
    assert default_lanes(10**7, 1, "gpu", per_lane, memory) == MAX_LANES_ARRAY
    big = 10**5  # a large state (sensitivities, say): the memory budget binds
    assert (
        default_lanes(10**7, 1, "gpu", big, memory)
        == int(MEMORY_SHARE * memory // (LANE_COPIES * big))
        < MAX_LANES_ARRAY
    )
    assert default_lanes(10**7, 1, "gpu", big, None) < default_lanes(
        10**7, 1, "gpu", big, memory
    )  # the fallback budget is smaller
    with pytest.raises(ValueError, match="`layout`"):
        rb.Lanes(layout="gpu")


def test_float32_initial_states_start_in_float64():
    """float32 `y0s` with a float64 model and times (the tests run with strict dtype
    promotion): both paths widen them to float64 before normalising (the lanes' buffers
    must hold the steps' states), so they take the same steps, and the solve equals one
    started from the widened float64 values."""
    y32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), initial_states())
    y64 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64), y32)  # exact
    kw = dict(rtol=RTOL, atol=RTOL)
    lanes = rb.simulate_batch(rb.RigidBody(J), y32, TS, batching=rb.Lanes(LANES), **kw)
    plain = rb.simulate_batch(rb.RigidBody(J), y32, TS, batching=rb.Vmap(), **kw)
    assert lanes.ys.omega.dtype == plain.ys.omega.dtype == jnp.float64
    assert_same_solves(lanes, plain)
    assert_same_solves(
        plain, rb.simulate_batch(rb.RigidBody(J), y64, TS, batching=rb.Vmap(), **kw), tol=0.0
    )


def test_argument_errors():
    y0s = initial_states()
    for solver in (diffrax.Kvaerno5(), diffrax.Euler(), diffrax.ReversibleHeun()):
        with pytest.raises(
            ValueError, match="explicit Runge–Kutta solver.*" + type(solver).__name__
        ):
            rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Lanes(LANES), solver=solver)
    for bad in (0, -3, True, 2.5):
        with pytest.raises(ValueError, match="`lanes`"):
            rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Lanes(bad))
    with pytest.raises(ValueError, match="`devices`"):
        rb.simulate_batch(
            rb.RigidBody(J), y0s, TS, batching=rb.Lanes(LANES, devices=len(jax.devices()) + 1)
        )


def test_two_devices_and_the_persistent_cache(tmp_path):
    """In a fresh process with two XLA host devices, the batch (odd: padded) is dealt to
    both and equals the plain solve, with a shared model and with per-trajectory models,
    and with inputs committed to one of the devices; the compiled program holds no host
    callback, so it is written to JAX's persistent compilation cache."""
    out = tmp_path / "lanes.npz"
    cache = tmp_path / "xla-cache"
    code = textwrap.dedent(f"""
        import jax
        jax.config.update("jax_enable_x64", True)
        jax.config.update("jax_compilation_cache_dir", {str(cache)!r})
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        assert jax.device_count() == 2
        import numpy as np, jax.numpy as jnp, rbdyn_jax as rb
        d = np.load({str(tmp_path / "in.npz")!r})
        tr = rb.simulate_batch(rb.RigidBody(jnp.asarray(d["J"])),
                               rb.State(jnp.asarray(d["w"]), jnp.asarray(d["q"])),
                               jnp.asarray(d["ts"]), rtol={RTOL}, atol={RTOL},
                               batching=rb.Lanes({LANES}))
        import equinox as eqx
        J = jnp.asarray(d["J"])
        tops = eqx.filter_vmap(lambda w: rb.RigidBody(J, rb.UniformGravity(
            w, jnp.array([0.0, 0.1, 0.5]))))(jnp.asarray(d["weights"]))
        tr2 = rb.simulate_batch(tops, rb.State(jnp.asarray(d["w"]), jnp.asarray(d["q"])),
                                jnp.asarray(d["ts"]), rtol={RTOL}, atol={RTOL},
                                batching=rb.Lanes({LANES}),
                                model_axes=0)
        # inputs committed to one device (by `jax.device_put`, or as a stored program's
        # outputs are) are placed on both
        one = jax.devices()[1]
        tr3 = rb.simulate_batch(rb.RigidBody(jax.device_put(J, one)),
                                jax.device_put(rb.State(jnp.asarray(d["w"]),
                                                        jnp.asarray(d["q"])), one),
                                jax.device_put(jnp.asarray(d["ts"]), one),
                                rtol={RTOL}, atol={RTOL}, batching=rb.Lanes({LANES}))
        np.savez({str(out)!r}, omega=tr.ys.omega, steps=tr.stats["num_steps"],
                 omega2=tr2.ys.omega, steps2=tr2.stats["num_steps"], omega3=tr3.ys.omega)
    """)
    y0s = initial_states()
    weights = jnp.linspace(0.5, 2.0, N)
    np.savez(tmp_path / "in.npz", J=J, w=y0s.omega, q=y0s.quat, ts=TS, weights=weights)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=300)
    got = np.load(out)
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, TS, rtol=RTOL, atol=RTOL, batching=rb.Vmap())
    np.testing.assert_array_equal(got["steps"], plain.stats["num_steps"])
    np.testing.assert_allclose(got["omega"], plain.ys.omega, rtol=0, atol=ROUND_OFF)
    np.testing.assert_array_equal(got["omega3"], got["omega"])  # the same program's bits
    # per-trajectory models are padded and dealt to the devices with their trajectories
    plain2 = rb.simulate_batch(
        eqx.filter_vmap(heavy_top)(weights),
        y0s,
        TS,
        rtol=RTOL,
        atol=RTOL,
        model_axes=0,
        batching=rb.Vmap(),
    )
    np.testing.assert_array_equal(got["steps2"], plain2.stats["num_steps"])
    np.testing.assert_allclose(got["omega2"], plain2.ys.omega, rtol=0, atol=ROUND_OFF)
    assert any(p.is_file() for p in cache.rglob("*")), "nothing entered the cache"


def test_two_devices_with_committed_inputs_and_throw(tmp_path):
    """The lane solver splitting a batch over two devices (no cache of traced programs):
    inputs a user committed to one device (`jax.device_put(x, device)`) are placed on both,
    with the same bits as uncommitted ones; and with `throw=True` a failed check raises,
    called eagerly and inside a caller's `jit`, rather than aborting the process (XLA does
    when a check raises on one device while the other waits for it)."""
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np
        import equinox as eqx
        import rbdyn_jax as rb
        jax.config.update("jax_enable_x64", True)
        assert jax.local_device_count() == 2
        w = np.ones((8, 3)); w[:, 1] = np.linspace(-1, 1, 8)
        y0s = rb.State(jnp.asarray(w), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (8, 1)))
        model, ts = rb.RigidBody(jnp.diag(jnp.array([1.0, 2.0, 3.0]))), jnp.linspace(0, 1, 3)
        free = rb.simulate_batch(model, y0s, ts).ys.omega
        one = jax.devices()[1]
        put = rb.simulate_batch(jax.device_put(model, one), jax.device_put(y0s, one),
                                jax.device_put(ts, one)).ys.omega
        assert np.array_equal(put, free)
        w[5, 0] = np.inf
        y0s = rb.State(jnp.asarray(w), y0s.quat)
        try:
            rb.simulate_batch(model, y0s, ts, throw=True)
        except eqx.EquinoxRuntimeError as e:
            assert "not finite" in str(e)
        else:
            raise AssertionError("no error")
        try:
            jax.jit(lambda y: rb.simulate_batch(model, y, ts, throw=True).ys.omega)(y0s)
        except Exception as e:
            assert "not finite" in str(e)
        else:
            raise AssertionError("no error")
        print("raised twice")
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, timeout=120, capture_output=True, text=True
    )
    assert out.returncode == 0 and "raised twice" in out.stdout, out.stderr[-2000:]
