"""`simulate_batch`'s batching strategies (`Lanes`, `Vmap`, the default) and its step-size
controller passed through.

That the two strategies give the same trajectories and derivatives is `test_lanes.py`'s
subject; here: which one the default takes, that the default call *is* that strategy's
call, and the errors a user meets.
"""

import logging

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb
from rbdyn_jax.integrate._batching import default_batching, default_lanes

J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
TS = jnp.linspace(0.0, 5.0, 11)
N = 9


def initial_states(n=N, seed=0):
    w = np.random.default_rng(seed).normal(size=(n, 3))
    return rb.State(jnp.asarray(w), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1)))


def same(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


PID = diffrax.PIDController(rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize(
    "solver, controller, adjoint, chosen",
    [
        (diffrax.Tsit5(), PID, None, rb.Lanes),
        (diffrax.Dopri8(), PID, None, rb.Lanes),
        (diffrax.Kvaerno5(), PID, None, rb.Vmap),  # implicit: no lane step
        (diffrax.Tsit5(), PID, diffrax.BacksolveAdjoint(), rb.Vmap),  # an adjoint asked for
        (diffrax.Tsit5(), diffrax.ConstantStepSize(), None, rb.Vmap),  # no rtol/atol to order by
    ],
)
def test_default_takes_lanes_only_where_they_can_run_the_solve(solver, controller, adjoint, chosen):
    assert type(default_batching(solver, controller, adjoint)) is chosen


def test_the_default_call_is_the_lane_solvers_call():
    y0s = initial_states()
    default = rb.simulate_batch(rb.RigidBody(J), y0s, TS)
    same(default, rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Lanes()))
    lanes = default_lanes(N, len(jax.local_devices()))
    same(default, rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Lanes(lanes)))


def test_an_adjoint_makes_the_default_the_vmapped_solve():
    y0s, adjoint = initial_states(), diffrax.RecursiveCheckpointAdjoint(checkpoints=64)
    same(
        rb.simulate_batch(rb.RigidBody(J), y0s, TS, adjoint=adjoint),
        rb.simulate_batch(rb.RigidBody(J), y0s, TS, adjoint=adjoint, batching=rb.Vmap()),
    )


def test_default_lanes_follow_the_batch_and_the_devices():
    # a few lanes for a small batch, ~2 trajectories a lane, capped; per device
    assert [default_lanes(n, 1) for n in (1, 4, 16, 64)] == [1, 4, 8, 32]
    assert default_lanes(10**6, 1) in (64, 256)  # the cap: XLA configured or not
    assert default_lanes(64, 2) == default_lanes(32, 1)
    lanes = [default_lanes(n, 1) for n in range(1, 2000, 7)]
    assert lanes == sorted(lanes)


@pytest.mark.parametrize(
    "batching, match",
    [
        (rb.Lanes(), "explicit Runge–Kutta"),
    ],
)
def test_lanes_refuse_an_implicit_solver(batching, match):
    with pytest.raises(ValueError, match=match):
        rb.simulate_batch(
            rb.RigidBody(J), initial_states(), TS, solver=diffrax.Kvaerno5(), batching=batching
        )


def test_lanes_refuse_an_adjoint_and_a_controller_without_tolerances():
    with pytest.raises(ValueError, match="takes no `adjoint`"):
        rb.simulate_batch(
            rb.RigidBody(J),
            initial_states(),
            TS,
            batching=rb.Lanes(),
            adjoint=diffrax.BacksolveAdjoint(),
        )
    with pytest.raises(ValueError, match="PIDController"):
        rb.simulate_batch(
            rb.RigidBody(J),
            initial_states(),
            TS,
            batching=rb.Lanes(),
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=0.01,
        )


@pytest.mark.parametrize("bad", [0, -1, 2.0, True, "64"])
def test_lanes_refuse_a_bad_count(bad):
    with pytest.raises(ValueError, match="`lanes` must be a positive int"):
        rb.Lanes(bad)
    with pytest.raises(ValueError, match="`devices` must be a positive int"):
        rb.Lanes(devices=bad)


def test_batching_must_be_a_strategy():
    with pytest.raises(ValueError, match="`batching` must be"):
        rb.simulate_batch(rb.RigidBody(J), initial_states(), TS, batching="lanes")


# ---------------------------------------------------------------------------------------
# The step-size controller, passed through
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("batching", [None, rb.Vmap()], ids=["default", "vmap"])
def test_a_pid_controller_is_the_same_solve_as_its_tolerances(batching):
    y0s = initial_states()
    by_tols = rb.simulate_batch(rb.RigidBody(J), y0s, TS, rtol=1e-6, atol=1e-9, batching=batching)
    by_controller = rb.simulate_batch(
        rb.RigidBody(J),
        y0s,
        TS,
        batching=batching,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-9),
    )
    same(by_tols, by_controller)
    one = rb.simulate(
        rb.RigidBody(J),
        jax.tree_util.tree_map(lambda x: x[0], y0s),
        TS,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-9),
    )
    np.testing.assert_allclose(one.ys.omega, by_tols.ys.omega[0], rtol=0, atol=1e-12)  # round-off


def test_the_controllers_options_reach_the_solve():
    """A controller is passed through whole: a step size cap (`dtmax`) shows in the steps
    taken, and a constant step size with `dt0` runs the vmapped solve."""
    y0s = initial_states()
    free = rb.simulate_batch(rb.RigidBody(J), y0s, TS)
    capped = rb.simulate_batch(
        rb.RigidBody(J),
        y0s,
        TS,
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8, dtmax=0.01),
    )
    assert np.all(capped.stats["num_steps"] >= 500) and np.all(free.stats["num_steps"] < 500)
    np.testing.assert_allclose(capped.ys.omega, free.ys.omega, rtol=0, atol=1e-6)  # rtol 1e-8
    fixed = rb.simulate_batch(
        rb.RigidBody(J), y0s, TS, dt0=5.0 / 500, stepsize_controller=diffrax.ConstantStepSize()
    )
    assert np.all(fixed.stats["num_steps"] == 500)
    np.testing.assert_allclose(fixed.ys.omega, free.ys.omega, rtol=0, atol=1e-6)


def test_tolerances_given_twice_or_not_a_controller_are_refused():
    y0 = jax.tree_util.tree_map(lambda x: x[0], initial_states())
    with pytest.raises(ValueError, match="not both"):
        rb.simulate(rb.RigidBody(J), y0, TS, rtol=1e-6, stepsize_controller=PID)
    with pytest.raises(ValueError, match="step-size controller"):
        rb.simulate(rb.RigidBody(J), y0, TS, stepsize_controller=1e-6)
    with pytest.raises(ValueError, match="`rtol` must be a positive"):
        rb.simulate(
            rb.RigidBody(J), y0, TS, stepsize_controller=diffrax.PIDController(rtol=-1.0, atol=1e-8)
        )


def test_new_controller_tolerances_do_not_recompile(caplog):
    y0s = initial_states()

    def run(tol):
        return rb.simulate_batch(
            rb.RigidBody(J), y0s, TS, stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol)
        )

    jax.block_until_ready(run(1e-7))
    caplog.clear()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        jax.block_until_ready(run(1e-9))
    assert sum("Compiling" in r.getMessage() for r in caplog.records) == 0
