"""The lane solver, `simulate_batch(..., lanes=L)`, against the plain vmapped `diffeqsolve`.

The lane solver drives diffrax's own solver step and PID controller, so it must take the
*same* steps as `diffeqsolve` for every trajectory — checked exactly through the step
counts — and save the same values: only round-off may differ (the interpolant's weights
are formed differently; measured ≤ 5e-15 on states of size ≲ 5). Covered: a shared model
and per-trajectory models (`model_axes=0`), a relative model in a moving frame (a
time-dependent right-hand side), Tsit5 and Dopri5 (different interpolants), more
trajectories than lanes (refilling), failure isolation (a non-finite start, a trajectory out
of steps), results independent of the batch order and of the lane a trajectory ran in,
forward-mode gradients against reverse mode and finite differences (and a jvp that writes
its tangents without touching the whole output buffer), two XLA host devices
(shared and per-trajectory models), input errors, and that the compiled program can enter
JAX's persistent cache.
"""

import os
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb

J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
TS = jnp.linspace(0.0, 6.0, 13)
N, LANES = 11, 4  # more trajectories than lanes, not a multiple: refills and idle lanes
RTOL = 1e-9
# Same steps (asserted exactly); the saved values differ by round-off only.
ROUND_OFF = 1e-12


def initial_states(n=N, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return rb.State(jnp.asarray(rng.normal(size=(n, 3))),
                    jnp.asarray(q / np.linalg.norm(q, axis=1, keepdims=True)))


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
        eqx.filter_vmap(heavy_top)(jnp.linspace(0.5, 2.0, N)), 0, diffrax.Dopri5()),
    # weight seen from a turning frame: the torque depends on t through the frame's attitude
    "relative_rotating_frame": lambda: (
        rb.RelativeRigidBody(J, rb.ConstantRate(jnp.array([0.0, 0.3, 1.0])),
                             rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5]))), None,
        diffrax.Tsit5()),
}


@pytest.mark.parametrize("case", CASES)
def test_same_steps_and_values_as_vmapped_diffeqsolve(case):
    model, axes, solver = CASES[case]()
    y0s = initial_states()
    kw = dict(model_axes=axes, solver=solver, rtol=RTOL, atol=RTOL)
    lanes = rb.simulate_batch(model, y0s, TS, lanes=LANES, **kw)
    plain = rb.simulate_batch(model, y0s, TS, **kw)
    assert np.all(plain.result._value == 0)
    assert_same_solves(lanes, plain)
    assert lanes.ys.omega.shape == (N, len(TS), 3)


def test_results_do_not_depend_on_the_order_of_the_batch_or_the_lane():
    """Lanes take trajectories longest-first (by |f(t0, y0)| in the tolerance scale).
    (1) A permuted batch gives the permuted results, to the bit: the bookkeeping returns
    every trajectory to its own row. (2) Replacing one trajectory by a fast spinner moves it
    to the front of the order, so every other trajectory runs in another lane and starts at
    another iteration; their results are unchanged to the bit (a lane's arithmetic is its
    own)."""
    y0s = initial_states()
    kw = dict(rtol=RTOL, atol=RTOL, lanes=LANES)
    a = rb.simulate_batch(rb.RigidBody(J), y0s, TS, **kw)
    perm = np.random.default_rng(3).permutation(N)
    b = rb.simulate_batch(rb.RigidBody(J), jax.tree_util.tree_map(lambda x: x[perm], y0s),
                          TS, **kw)
    for x, y in zip(jax.tree_util.tree_leaves((a.ys, a.stats)),
                    jax.tree_util.tree_leaves((b.ys, b.stats))):
        np.testing.assert_array_equal(np.asarray(x)[perm], y)
    assert np.argmax(a.stats["num_steps"]) != 5  # it moves up the order: the rest move down
    spinner = rb.State(y0s.omega.at[5].set(jnp.array([0.3, 6.0, 1.0])), y0s.quat)
    c = rb.simulate_batch(rb.RigidBody(J), spinner, TS, **kw)
    assert c.stats["num_steps"][5] > np.max(np.delete(np.asarray(a.stats["num_steps"]), 5))
    keep = np.arange(N) != 5
    for x, y in zip(jax.tree_util.tree_leaves((a.ys, a.stats)),
                    jax.tree_util.tree_leaves((c.ys, c.stats))):
        np.testing.assert_array_equal(np.asarray(x)[keep], np.asarray(y)[keep])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_floats_below_is_diffrax_clip_floor(dtype):
    """The lane solver's end-of-interval clip (a step ending within 100 floats of t1 ends
    at t1) computes diffeqsolve's threshold, t1 moved down by 100 calls of equinox's
    `prevbefore`, by integer arithmetic on the float's bits. It must equal that loop, and
    NumPy's `nextafter` away from 0, across binade edges (powers of 2), at signed zero and
    for negative times; no tangent flows through it. (Not compared: inputs within 100
    floats of the subnormal range, where XLA:CPU flushes subnormal results to zero and the
    loop's result depends on it; no solve ends there.)"""
    from equinox.internal import prevbefore

    from rbdyn_jax.integrate import _floats_below

    rng = np.random.default_rng(1)
    xs = np.concatenate([
        rng.normal(size=40) * 10.0 ** rng.uniform(-6, 6, 40),
        [0.0, -0.0, 1.0, 2.0, 1024.0, -1.0, -2.0, 6.0, 20.0, 100.0, 1e-30, -1e-30],
    ]).astype(dtype)
    below = jax.jit(_floats_below, static_argnums=1)
    for k in (1, 2, 100):
        want = jnp.asarray(xs)
        for _ in range(k):
            want = prevbefore(want)
        want = np.asarray(want)
        got = np.asarray(below(jnp.asarray(xs), k))
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))
        away = xs != 0
        numpy_want = xs[away]
        for _ in range(k):
            numpy_want = np.nextafter(numpy_want, dtype(-np.inf))
        np.testing.assert_array_equal(got[away], numpy_want)
    _, tangent = jax.jvp(lambda x: _floats_below(x, 100), (jnp.asarray(xs),),
                         (jnp.ones_like(jnp.asarray(xs)),))
    np.testing.assert_array_equal(tangent, 0.0)


def test_vmap_over_the_lane_solver_gives_each_member_its_own_solve():
    """`jax.vmap` over a lane solve (here over the weight of a heavy top that the whole
    batch shares) must give each member exactly its own solve: the loop's state carries are
    tied to the inputs from the start (so that JAX's batching fixpoint converges in one
    pass), and every carry that depends on the mapped weight must be batched, while the
    members' step counts differ."""
    weights = jnp.array([0.5, 3.0])
    y0s = initial_states()

    def solve(w):
        return rb.simulate_batch(heavy_top(w), y0s, TS, rtol=RTOL, atol=RTOL, lanes=LANES)

    both = jax.vmap(solve)(weights)
    alone = [solve(w) for w in weights]
    assert np.any(alone[0].stats["num_steps"] != alone[1].stats["num_steps"])
    for i, one in enumerate(alone):
        assert_same_solves(jax.tree_util.tree_map(lambda x, i=i: x[i], both), one)


def test_failures_stay_in_their_lane():
    """A NaN start is `nonfinite_state`, a fast spinner runs out of steps; the lanes they
    shared go on with other trajectories, which equal the plain solve."""
    y0s = initial_states()
    omega = y0s.omega.at[2].set(jnp.nan).at[7].set(jnp.array([0.0, 400.0, 1.0]))
    y0s = rb.State(omega, y0s.quat)
    kw = dict(rtol=RTOL, atol=RTOL, max_steps=300)
    lanes = rb.simulate_batch(rb.RigidBody(J), y0s, TS, lanes=LANES, **kw)
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, TS, **kw)
    codes = np.asarray(lanes.result._value)
    assert codes[2] == rb.RESULTS.nonfinite_state._value
    assert codes[7] == rb.RESULTS.max_steps_reached._value
    assert np.sum(codes == 0) == N - 2
    assert_same_solves(lanes, plain)


def test_forward_mode_gradient_matches_reverse_mode_and_finite_differences():
    """d/dθ of a batched loss, θ the log-Cholesky inertia parameters: `jax.jacfwd` through
    the lane solver vs `jax.grad` through the vmapped `diffeqsolve` (reverse mode) and vs
    central differences. Both autodiff paths differentiate the same discrete steps (the
    controller's step-size factor is not differentiated in either), so they agree to
    round-off; the finite differences (h = 1e-6 on O(1) θ, solves at rtol 1e-11) carry
    O(h²) + rtol/h ≈ 1e-5 relative error."""
    y0s = initial_states(6, seed=1)
    ts = jnp.linspace(0.0, 3.0, 7)
    # data from a different body (not a multiple of J: torque-free ω(t) is scale-free)
    J_data = J + jnp.diag(jnp.array([0.1, 0.0, 0.0]))
    obs = rb.simulate_batch(rb.RigidBody(J_data), y0s, ts, rtol=1e-11, atol=1e-11).ys.omega
    theta0 = rb.inertia.to_log_cholesky(J)

    def loss(theta, lanes):
        model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
        tr = rb.simulate_batch(model, y0s, ts, rtol=1e-11, atol=1e-11, lanes=lanes)
        return jnp.sum((tr.ys.omega - obs) ** 2)

    fwd = jax.jit(jax.jacfwd(lambda th: loss(th, LANES)))(theta0)
    rev = jax.jit(jax.grad(lambda th: loss(th, None)))(theta0)
    assert float(jnp.max(jnp.abs(rev))) > 1e-2  # a real gradient, not round-off
    np.testing.assert_allclose(fwd, rev, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(rev))))
    f = jax.jit(lambda th: loss(th, LANES))
    h = 1e-6
    fd = np.array([(f(theta0.at[i].add(h)) - f(theta0.at[i].add(-h))) / (2 * h)
                   for i in range(theta0.shape[0])])
    np.testing.assert_allclose(fwd, fd, rtol=1e-4, atol=1e-5 * np.max(np.abs(fd)))


def _scatters(jaxpr):
    """Every scatter-like equation in `jaxpr` and its sub-jaxprs (loop bodies, …)."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name.startswith("scatter"):
            yield eqn
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            yield from _scatters(sub)


def test_forward_mode_saves_tangents_without_touching_the_whole_output():
    """The jvp of the lane loop writes each saved tangent where the value goes, as the
    primal does. A scatter without `unique_indices` would instead get JAX's general JVP:
    ids scattered into a buffer the size of the whole output, then a masked scatter-add,
    at every loop iteration — correct, but a cost quadratic in the batch size (measured
    10.0× the forward solve for a jvp of 8192 trajectories, against 1.85×). The value
    tests above cannot see that, so the program is inspected: every float scatter in the
    jvp is a plain `scatter` promising unique indices, and there is no scatter-add."""
    y0s = initial_states()

    def omega(J):
        return rb.simulate_batch(rb.RigidBody(J), y0s, TS, rtol=RTOL, atol=RTOL,
                                 lanes=LANES).ys.omega

    jaxpr = jax.make_jaxpr(lambda J, dJ: jax.jvp(omega, (J,), (dJ,)))(J, jnp.eye(3))
    floats = [e for e in _scatters(jaxpr.jaxpr)
              if jnp.issubdtype(e.invars[0].aval.dtype, jnp.floating)]
    assert floats  # the saved values (and their tangents) are there to check
    for e in floats:
        assert e.primitive.name == "scatter", e.primitive.name
        assert e.params["unique_indices"], e


def test_argument_errors():
    y0s = initial_states()
    for bad in (0, -3, True, 2.5):
        with pytest.raises(ValueError, match="`lanes`"):
            rb.simulate_batch(rb.RigidBody(J), y0s, TS, lanes=bad)
    with pytest.raises(ValueError, match="`devices`"):
        rb.simulate_batch(rb.RigidBody(J), y0s, TS, lanes=LANES, devices=len(jax.devices()) + 1)


def test_two_devices_and_the_persistent_cache(tmp_path):
    """In a fresh process with two XLA host devices, the batch (odd: padded) is dealt to
    both and equals the plain solve, with a shared model and with per-trajectory models;
    the compiled program holds no host callback, so it is written to JAX's persistent
    compilation cache."""
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
                               jnp.asarray(d["ts"]), rtol={RTOL}, atol={RTOL}, lanes={LANES})
        import equinox as eqx
        J = jnp.asarray(d["J"])
        tops = eqx.filter_vmap(lambda w: rb.RigidBody(J, rb.UniformGravity(
            w, jnp.array([0.0, 0.1, 0.5]))))(jnp.asarray(d["weights"]))
        tr2 = rb.simulate_batch(tops, rb.State(jnp.asarray(d["w"]), jnp.asarray(d["q"])),
                                jnp.asarray(d["ts"]), rtol={RTOL}, atol={RTOL}, lanes={LANES},
                                model_axes=0)
        np.savez({str(out)!r}, omega=tr.ys.omega, steps=tr.stats["num_steps"],
                 omega2=tr2.ys.omega, steps2=tr2.stats["num_steps"])
    """)
    y0s = initial_states()
    weights = jnp.linspace(0.5, 2.0, N)
    np.savez(tmp_path / "in.npz", J=J, w=y0s.omega, q=y0s.quat, ts=TS, weights=weights)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=300)
    got = np.load(out)
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, TS, rtol=RTOL, atol=RTOL)
    np.testing.assert_array_equal(got["steps"], plain.stats["num_steps"])
    np.testing.assert_allclose(got["omega"], plain.ys.omega, rtol=0, atol=ROUND_OFF)
    # per-trajectory models are padded and dealt to the devices with their trajectories
    plain2 = rb.simulate_batch(eqx.filter_vmap(heavy_top)(weights), y0s, TS, rtol=RTOL,
                               atol=RTOL, model_axes=0)
    np.testing.assert_array_equal(got["steps2"], plain2.stats["num_steps"])
    np.testing.assert_allclose(got["omega2"], plain2.ys.omega, rtol=0, atol=ROUND_OFF)
    assert any(p.is_file() for p in cache.rglob("*")), "nothing entered the cache"
