"""The solves on a GPU (marked `gpu`: run where JAX's default backend is one, skipped
elsewhere). This module imports only JAX, diffrax and NumPy beside rbdyn_jax, so that it
runs on a GPU machine without the sweep's store libraries.

On a GPU the default `simulate_batch` takes the Pallas kernel (`Kernel`, Triton's
lowering); the lane solver there takes its array layout with a lane for every trajectory of
a small batch (`Lanes`, `default_lanes`). Checked there: that the default call is the
kernel's solve, and `Lanes()` the lane-per-trajectory one; that the default takes the
same steps as the vmapped `diffeqsolve` on the same GPU and the same values to round-off;
that its accuracy against the Jacobi elliptic solution is what the tolerance gives; that
gradients through it (the kernel's forward sensitivities) equal reverse mode through the
vmapped `diffeqsolve`; and that float32 solves reach the accuracy the docs state.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb
from rbdyn_jax.integrate._batching import default_lanes, device_memory, lane_bytes

pytestmark = pytest.mark.gpu

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
N = 512
TS = np.linspace(0.0, 20.0, 41)
TOL = 1e-8


def states(n=N, dtype=np.float64, seed=0):
    w = np.random.default_rng(seed).normal(size=(n, 3)).astype(dtype)
    q = np.tile(np.array([1.0, 0.0, 0.0, 0.0], dtype), (n, 1))
    return rb.State(jnp.asarray(w), jnp.asarray(q))


def elliptic(y0s, ts):
    moments, axes = rb.inertia.principal_axes(jnp.asarray(J))
    return (
        jax.vmap(lambda w: rb.analytic.torque_free_elliptic(moments, w, jnp.asarray(ts)))(
            y0s.omega @ axes
        )
        @ axes.T
    )


def test_the_default_is_the_kernel_and_lanes_a_lane_per_trajectory():
    y0s = states()
    lanes = default_lanes(N, 1, "gpu", lane_bytes(y0s), device_memory(jax.devices()[0]))
    assert lanes == N
    model, ts = rb.RigidBody(jnp.asarray(J)), jnp.asarray(TS)
    for batching, explicit in ((None, rb.Kernel()), (rb.Lanes(), rb.Lanes(N, layout="array"))):
        a = rb.simulate_batch(model, y0s, ts, batching=batching)
        b = rb.simulate_batch(model, y0s, ts, batching=explicit)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_same_steps_as_vmapped_diffeqsolve_and_the_elliptic_solution():
    """Same steps (exactly) and values to round-off as the vmapped `diffeqsolve` on the
    GPU; both within the tolerance's reach of the closed form (rtol 1e-8 over 20 s of
    O(1) rates: ≲ 1e-5, as on a CPU)."""
    y0s, ts = states(), jnp.asarray(TS)
    default = rb.simulate_batch(rb.RigidBody(jnp.asarray(J)), y0s, ts, rtol=TOL, atol=TOL)
    plain = rb.simulate_batch(
        rb.RigidBody(jnp.asarray(J)), y0s, ts, rtol=TOL, atol=TOL, batching=rb.Vmap()
    )
    for k in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        np.testing.assert_array_equal(default.stats[k], plain.stats[k])
    np.testing.assert_allclose(default.ys.omega, plain.ys.omega, rtol=0, atol=1e-11)
    err = np.max(np.abs(np.asarray(default.ys.omega) - np.asarray(elliptic(y0s, ts))))
    assert err < 1e-5


def test_gradient_equals_reverse_mode_through_vmapped_diffeqsolve():
    y0s, ts = states(64), jnp.asarray(TS[:11])
    theta0 = rb.inertia.to_log_cholesky(jnp.asarray(J))

    def loss(theta, batching):
        model = rb.with_log_cholesky(rb.RigidBody(jnp.asarray(J)), theta)
        tr = rb.simulate_batch(model, y0s, ts, rtol=1e-10, atol=1e-10, batching=batching)
        return jnp.sum(jnp.sin(tr.ys.omega)) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    lanes = jax.jit(jax.grad(lambda th: loss(th, None)))(theta0)
    plain = jax.jit(jax.grad(lambda th: loss(th, rb.Vmap())))(theta0)
    assert float(jnp.max(jnp.abs(plain))) > 1e-2
    np.testing.assert_allclose(lanes, plain, rtol=1e-8, atol=1e-11)


def test_float32_reaches_the_stated_accuracy():
    """float32 at rtol = atol = 1e-6 against the float64 solve at 1e-12: the median
    trajectory's largest error over 20 s stays under 1e-4 (the performance page's
    float32 figures)."""
    ts32 = jnp.asarray(TS, jnp.float32)
    y32 = states(dtype=np.float32)
    tr = rb.simulate_batch(
        rb.RigidBody(jnp.asarray(J, jnp.float32)), y32, ts32, rtol=1e-6, atol=1e-6
    )
    assert tr.ys.omega.dtype == jnp.float32
    assert bool(jnp.all(tr.result == rb.RESULTS.successful))
    ref = elliptic(states(), jnp.asarray(TS))
    err = np.max(np.abs(np.asarray(tr.ys.omega, np.float64) - np.asarray(ref)), axis=(1, 2))
    assert np.median(err) < 1e-4
