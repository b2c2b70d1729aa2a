"""The kernel strategy, `simulate_batch(..., batching=rb.Kernel())`, in Pallas's interpret
mode on the CPU, against `batching=rb.Vmap()`, the vmapped `diffeqsolve`.

The kernel drives diffrax's step-size controller and the solver's tableau per lane, so it
must take the *same* steps as `diffeqsolve` for every trajectory (step counts and
accept/reject decisions asserted exactly) and save the same values to round-off: its
stages are unrolled sums (diffrax's step is a loop of dot products over a stage buffer)
and a 3×3 contraction is a sum of rows, so the last bits differ, and the difference grows
along a trajectory with its error propagation. `ROUND_OFF` is the bound the lane solver's
tests use for the same difference. Small batches (8–12) and short horizons: each solve
runs in seconds in interpret mode.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb

J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
TS = jnp.linspace(0.0, 3.0, 7)
N = 10  # not a power of two: the batch is padded to the block
RTOL = 1e-9
# Same steps (asserted exactly); the saved values differ by round-off only (states of
# size ≲ 3 here; measured ≤ 5e-14).
ROUND_OFF = 1e-12
# The gradient tests' own jits (of a kernel in interpret mode and of the lane solver they
# compare it with) compile at XLA's backend optimisation level 0, in about half the time;
# they compare values to a tolerance, never steps decided in float32.
QUICK = {"xla_backend_optimization_level": 0}


def initial_states(n=N, seed=0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return rb.State(
        jnp.asarray(rng.normal(size=(n, 3)), dtype),
        jnp.asarray(q / np.linalg.norm(q, axis=1, keepdims=True), dtype),
    )


def assert_same_solves(a, b, tol=ROUND_OFF):
    for k in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        np.testing.assert_array_equal(a.stats[k], b.stats[k], err_msg=k)
    np.testing.assert_array_equal(a.result._value, b.result._value)
    for x, y in zip(jax.tree_util.tree_leaves(a.ys), jax.tree_util.tree_leaves(b.ys)):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_allclose(x, y, rtol=0, atol=tol, equal_nan=True)
    np.testing.assert_allclose(a.stats["norm_drift"], b.stats["norm_drift"], atol=tol)


def heavy_top(weight):
    return rb.RigidBody(J, rb.UniformGravity(weight, jnp.array([0.0, 0.1, 0.5])))


CASES = {
    "torque_free_tsit5": lambda: (rb.RigidBody(J), None, diffrax.Tsit5()),
    "torque_free_bosh3": lambda: (rb.RigidBody(J), None, diffrax.Bosh3()),
    "heavy_top_per_trajectory_dopri5": lambda: (
        eqx.filter_vmap(heavy_top)(jnp.linspace(0.5, 2.0, N)),
        0,
        diffrax.Dopri5(),
    ),
    "torque_sum_tsit5": lambda: (
        rb.RigidBody(
            J,
            rb.GravityGradient(0.3)
            + rb.BodyTorque(jnp.array([0.1, 0.0, -0.2]))
            + rb.InertialTorque(jnp.array([0.0, 0.05, 0.1])),
        ),
        None,
        diffrax.Tsit5(),
    ),
    # k(τ, ψ) a polynomial: a `scan` in the field, unrolled on rows
    "restoring_polynomial_tsit5": lambda: (
        rb.RigidBody(J, rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([1.0, 0.5, 0.2]), 0.1))),
        None,
        diffrax.Tsit5(),
    ),
    # weight seen from a turning frame: the torque depends on t through the frame's attitude
    "relative_rotating_frame_tsit5": lambda: (
        rb.RelativeRigidBody(
            J,
            rb.ConstantRate(jnp.array([0.0, 0.3, 1.0])),
            rb.UniformGravity(1.0, jnp.array([0.0, 0.1, 0.5])),
        ),
        None,
        diffrax.Tsit5(),
    ),
    "orbit_gravity_gradient_balanced_tsit5": lambda: (
        rb.RelativeRigidBody(
            J, rb.CircularOrbit(0.5), rb.GravityGradient(0.75) + rb.BalancingTransport()
        ),
        None,
        diffrax.Tsit5(),
    ),
    "torque_free_dopri8": lambda: (rb.RigidBody(J), None, diffrax.Dopri8()),
}
# Where the round-off grows further (measured, with a margin of 4 or more):
TOL = {
    # the relative field's longer chain of operations (transport and Coriolis terms):
    # 1.1e-12 measured
    "relative_rotating_frame_tsit5": 5e-12,
    # Dopri8's 7th-order interpolant weighs the stages by large coefficients of both signs,
    # which multiply the stages' round-off (unrolled sums here, dot products in diffrax's
    # step), and its steps are long here (6–15 over the span): 4e-9 at outputs inside a
    # step, 1e-12 at a step's end; the lane solver's array layout (the same unrolled
    # stages) is as far from `Vmap` (4.0e-9), and 8e-11 from the kernel.
    "torque_free_dopri8": 2e-8,
}


@pytest.mark.parametrize("case", CASES)
def test_same_steps_and_values_as_vmapped_diffeqsolve(case):
    """From a start time that is not 0 (the field is read at t0 + s·span); four solvers
    (their tableaus and interpolants), a shared and a per-trajectory model, a sum of
    torques, a polynomial restoring moment, relative models in a turning frame and on a
    circular orbit. Each is a model the default takes the kernel for on a GPU: its field
    and the field's derivative run on rows (`field_refuse`)."""
    from rbdyn_jax.integrate._kernel_refusal import field_refuse

    model, axes, solver = CASES[case]()
    y0s = initial_states()
    assert field_refuse(model, y0s, axes) is None
    ts = TS + 1.5
    kw = dict(model_axes=axes, solver=solver, rtol=RTOL, atol=RTOL)
    kernel = rb.simulate_batch(model, y0s, ts, batching=rb.Kernel(), **kw)
    plain = rb.simulate_batch(model, y0s, ts, batching=rb.Vmap(), **kw)
    assert np.all(plain.result._value == 0)
    assert_same_solves(kernel, plain, TOL.get(case, ROUND_OFF))
    assert kernel.ys.omega.shape == (N, len(TS), 3)


def test_blocks_of_the_batch_and_the_default_on_a_faked_gpu_give_the_same_solves(monkeypatch):
    """Several programs (blocks of 4, the batch padded from 10 to 12): each trajectory's
    solve is its own, to the bit, whatever block it ran in. With JAX's backend reported as
    a GPU, `simulate_batch`'s default runs the kernel (here in interpret mode, asked for:
    the CPU has no Triton) and gives its solve."""
    import rbdyn_jax.integrate._batching as batching

    y0s = initial_states()
    kw = dict(rtol=RTOL, atol=RTOL)
    one = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Kernel(), **kw)
    blocks = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Kernel(block=4), **kw)
    monkeypatch.setattr(batching, "Kernel", lambda: rb.Kernel(interpret=True))
    monkeypatch.setattr(batching.jax, "default_backend", lambda: "gpu")
    default = rb.simulate_batch(rb.RigidBody(J), y0s, TS, **kw)
    for other in (blocks, default):
        for x, y in zip(
            jax.tree_util.tree_leaves((one.ys, one.stats)),
            jax.tree_util.tree_leaves((other.ys, other.stats)),
        ):
            np.testing.assert_array_equal(x, y)


def test_failures_stay_in_their_lane():
    """A NaN start is `nonfinite_state`, a fast spinner runs out of steps (its unsaved rows
    are NaN as `Vmap`'s); the lanes of its block go on and equal the plain solve."""
    y0s = initial_states()
    omega = y0s.omega.at[2].set(jnp.nan).at[7].set(jnp.array([0.0, 400.0, 1.0]))
    y0s = rb.State(omega, y0s.quat)
    kw = dict(rtol=RTOL, atol=RTOL, max_steps=300)
    kernel = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Kernel(), **kw)
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Vmap(), **kw)
    codes = np.asarray(kernel.result._value)
    assert codes[2] == rb.RESULTS.nonfinite_state._value
    assert codes[7] == rb.RESULTS.max_steps_reached._value
    assert np.sum(codes == 0) == N - 2
    assert kernel.stats["num_steps"][7] == 300
    assert_same_solves(kernel, plain)


def test_the_devices_share_the_batch_to_the_bit():
    """`Kernel(devices=2)` deals the batch out over the two host devices (11 trajectories:
    one padded), each running the kernel on its share: every trajectory's solve is its
    own, so the values, stats and codes equal one device's to the bit, for a model per
    trajectory and with a failing trajectory, and so does the gradient. The one-device
    solve is `Kernel()` under `jax.default_device`, which the kernel keeps to."""
    n = 11
    y0s = initial_states(n)
    y0s = rb.State(y0s.omega.at[4].set(jnp.nan), y0s.quat)
    models = eqx.filter_vmap(heavy_top)(jnp.linspace(0.5, 2.0, n))
    kw = dict(rtol=RTOL, atol=RTOL, model_axes=0)

    with jax.default_device(jax.devices()[1]):
        one = rb.simulate_batch(models, y0s, TS, batching=rb.Kernel(), **kw)
    assert one.ys.omega.sharding.device_set == {jax.devices()[1]}
    two = rb.simulate_batch(models, y0s, TS, batching=rb.Kernel(devices=2), **kw)
    assert len(two.ys.omega.sharding.device_set) == 2
    assert int(one.result._value[4]) == rb.RESULTS.nonfinite_state._value
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(two)):
        np.testing.assert_array_equal(a, b)

    def loss(weights, devices):
        m = eqx.filter_vmap(heavy_top)(weights)
        tr = rb.simulate_batch(m, y0s, TS, batching=rb.Kernel(devices=devices), **kw)
        return jnp.sum(jnp.where(jnp.isfinite(tr.ys.omega), tr.ys.omega, 0.0) ** 2)

    weights = jnp.linspace(0.5, 2.0, n)
    g1, g2 = jax.grad(loss)(weights, 1), jax.grad(loss)(weights, 2)
    assert np.count_nonzero(g1) == n - 1  # the failed trajectory's weight moves nothing
    np.testing.assert_array_equal(g1, g2)
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="`devices`"):
            rb.Kernel(devices=bad)
    with pytest.raises(ValueError, match="`devices`"):
        rb.simulate_batch(models, y0s, TS, batching=rb.Kernel(devices=3), **kw)


def test_float32():
    """float32 inputs solve in float32 (the default tolerance 1e-6), with `Vmap`'s steps
    to float32's rounding. XLA rounds the kernel's program and `Vmap`'s differently (where
    it fuses a product into a multiply-add), by float32's ε = 1.2e-7, a tenth of the
    tolerance: near it, that turns a step's acceptance, and a trajectory takes a step more
    or fewer (measured: one, in 3 to 11 of 64 trajectories over four seeds; never in
    float64, whose rounding is 1e-8 of its tolerance). The values then agree to the
    solves' error, not to round-off: measured ≤ 7e-6 over t ∈ [0, 3]."""
    y0s = initial_states(n=64, dtype=np.float32)
    ts = np.linspace(0.0, 3.0, 7, dtype=np.float32)
    model = rb.RigidBody(np.asarray(J, np.float32))
    kernel = rb.simulate_batch(model, y0s, ts, batching=rb.Kernel())
    plain = rb.simulate_batch(model, y0s, ts, batching=rb.Vmap())
    assert kernel.ys.omega.dtype == kernel.ys.quat.dtype == jnp.float32
    assert np.all(plain.result._value == 0) and np.all(kernel.result._value == 0)
    for k in ("num_steps", "num_accepted_steps", "num_rejected_steps"):
        diff = np.abs(np.asarray(kernel.stats[k]) - np.asarray(plain.stats[k]))
        assert np.max(diff) <= 1 and np.mean(diff != 0) < 0.25, k
    for x, y in zip(jax.tree_util.tree_leaves(kernel.ys), jax.tree_util.tree_leaves(plain.ys)):
        np.testing.assert_allclose(x, y, rtol=0, atol=2e-5)


def test_float32_times_with_a_float64_state():
    """float32 output times with a float64 model and state (JAX's standard promotion, as
    diffrax needs for them): the solve and its saved states are float64, as `Vmap`'s,
    with the same steps."""
    model, y0s = rb.RigidBody(J), initial_states()
    ts = np.linspace(0.0, 3.0, 7, dtype=np.float32)
    with jax.numpy_dtype_promotion("standard"):
        kernel = rb.simulate_batch(model, y0s, ts, rtol=RTOL, atol=RTOL, batching=rb.Kernel())
        plain = rb.simulate_batch(model, y0s, ts, rtol=RTOL, atol=RTOL, batching=rb.Vmap())
    assert kernel.ys.omega.dtype == plain.ys.omega.dtype == jnp.float64
    # Same steps; the values differ by the rounding of the float32 times themselves (the
    # kernel reads them in unit time, diffrax as they are): ε₃₂·|t|·|ẏ| ≲ 6e-8·3·3 ≈ 5e-7.
    assert_same_solves(kernel, plain, tol=1e-6)


class _Looped(rb.AbstractTorque):
    """A torque whose evaluation holds a while loop: no form on rows of lanes."""

    def __call__(self, kin, inertia):
        return jax.lax.while_loop(lambda m: jnp.sum(m) > 1.0, lambda m: 0.5 * m, kin.omega)


def test_what_the_kernel_cannot_run_is_refused_by_name():
    y0s = initial_states(4)
    with pytest.raises(ValueError, match="Kvaerno5"):
        rb.simulate_batch(rb.RigidBody(J), y0s, TS, solver=diffrax.Kvaerno5(), batching=rb.Kernel())
    with pytest.raises(ValueError, match="ConstantStepSize"):
        rb.simulate_batch(
            rb.RigidBody(J),
            y0s,
            TS,
            dt0=0.1,
            stepsize_controller=diffrax.ConstantStepSize(),
            batching=rb.Kernel(),
        )
    with pytest.raises(ValueError, match="while"):
        rb.simulate_batch(rb.RigidBody(J, _Looped()), y0s, TS, batching=rb.Kernel())
    for bad in (3, 0, True, 2.0):
        with pytest.raises(ValueError, match="power of two"):
            rb.Kernel(block=bad)


class _Tabulated(eqx.Module):
    """A model holding an array as a static field (hashed by its structure, but not
    comparable to another: `==` is elementwise)."""

    body: rb.RigidBody
    table: np.ndarray = eqx.field(static=True)

    def vector_field(self, t, y, args):
        return self.body.vector_field(t, y, args)


@jax.custom_jvp
def _soft(x):
    return jnp.tanh(x)


@_soft.defjvp
def _soft_jvp(primals, tangents):  # a rule holding a while loop: no form on rows
    (x,), (dx,) = primals, tangents
    d, _ = jax.lax.while_loop(
        lambda c: c[1] < 2, lambda c: (c[0], c[1] + 1), (1.0 - jnp.tanh(x) ** 2, 0)
    )
    return _soft(x), d * dx


class _SoftDamping(rb.AbstractTorque):
    """A torque c·tanh(ω) whose derivative (a `custom_jvp` rule) has no form on rows."""

    c: jax.Array

    def __call__(self, kin, inertia):
        return -self.c * _soft(kin.omega)


def test_a_derivative_with_no_form_on_rows_makes_the_default_take_lanes(monkeypatch):
    """A field whose values run on rows but whose derivative does not (a `custom_jvp` rule
    with a while loop): the kernel refuses its gradient by name; the default on a GPU
    (faked) takes `Lanes` for it, so that `jax.grad` through the
    default call works, equal to diffrax's forward mode through `Vmap` (the same discrete
    solve: measured 6e-16 relative; bound 1e-9 as the lane solver's own gradient tests)."""
    import rbdyn_jax.integrate._batching as batching

    y0s, c = initial_states(4), jnp.array([0.1, 0.2, 0.3])
    kw = dict(rtol=RTOL, atol=RTOL)

    def loss(c, batching=None, adjoint=None):
        model = rb.RigidBody(J, _SoftDamping(c))
        tr = rb.simulate_batch(model, y0s, TS, batching=batching, adjoint=adjoint, **kw)
        return jnp.sum(tr.ys.omega[:, -1] ** 2)

    kernel = rb.Kernel(interpret=True)
    with pytest.raises(ValueError, match="while"):
        jax.grad(loss)(c, kernel)
    monkeypatch.setattr(batching, "Kernel", lambda: kernel)
    monkeypatch.setattr(batching.jax, "default_backend", lambda: "gpu")
    assert "derivative" in batching.field_refuse(rb.RigidBody(J, _SoftDamping(c)), y0s, None)
    assert isinstance(
        batching.default_batching(
            diffrax.Tsit5(),
            rb.integrate.make_controller(**kw),
            None,
            rb.RigidBody(J, _SoftDamping(c)),
            y0s,
        ),
        rb.Lanes,
    )
    got = jax.jit(jax.grad(loss))(c)
    ref = jax.jit(jax.jacfwd(loss), static_argnums=(1, 2))(c, rb.Vmap(), diffrax.ForwardMode())
    assert np.min(np.abs(ref)) > 1e-3
    np.testing.assert_allclose(got, ref, rtol=1e-9)


def test_the_fields_verdict_is_kept_per_structure():
    """`field_refuse` decides once per structure, static values, shapes and dtypes: the
    same verdict for another model of that structure, its own for another structure, and
    a verdict traced anew where a static value cannot be compared."""
    from rbdyn_jax.integrate import _kernel_refusal

    y0s = initial_states(4)
    _kernel_refusal._VERDICTS.clear()
    assert _kernel_refusal.field_refuse(rb.RigidBody(J), y0s, None) is None
    assert _kernel_refusal.field_refuse(rb.RigidBody(2.0 * J), y0s, None) is None
    assert len(_kernel_refusal._VERDICTS) == 1
    assert "while" in _kernel_refusal.field_refuse(rb.RigidBody(J, _Looped()), y0s, None)
    assert len(_kernel_refusal._VERDICTS) == 2
    with warnings.catch_warnings():  # equinox warns of an array as a static value
        warnings.simplefilter("ignore")
        table = _Tabulated(rb.RigidBody(J), np.arange(3.0))
    for _ in range(2):  # the second lookup compares the arrays (ambiguous): traced again
        assert _kernel_refusal.field_refuse(table, y0s, None) is None


def _k(tau, psi):
    return 0.5 + 0.1 * jnp.sin(psi)


def test_the_default_takes_the_kernel_only_on_a_gpu_backend():
    """`simulate_batch`'s default (`default_batching`): `Kernel` on a GPU backend (faked
    here: the choice reads the backend's name) where it can run the solve; `Lanes` on a
    CPU, or on a GPU for a field with no form on rows or an error norm of the user's;
    `Vmap` for an implicit solver."""
    from rbdyn_jax.integrate._batching import default_batching

    y0s, pid = initial_states(4), rb.integrate.make_controller(rtol=RTOL, atol=RTOL)

    def chosen(model, backend, solver=diffrax.Tsit5(), model_axes=None):
        return type(default_batching(solver, pid, None, model, y0s, model_axes, backend=backend))

    assert chosen(rb.RigidBody(J), "gpu") is rb.Kernel
    assert (
        chosen(eqx.filter_vmap(heavy_top)(jnp.linspace(0.5, 2.0, 4)), "gpu", model_axes=0)
        is rb.Kernel
    )
    # a batch of models sharing a leaf that is no array (a plain function k(τ, ψ))
    k_models = eqx.filter_vmap(lambda e: rb.RigidBody(J, rb.RestoringMoment(_k, e)))(
        jnp.linspace(0.1, 0.4, 4)
    )
    assert chosen(k_models, "gpu", model_axes=0) is rb.Kernel
    assert chosen(rb.RigidBody(J), "cpu") is rb.Lanes
    assert chosen(rb.RigidBody(J, _Looped()), "gpu") is rb.Lanes
    assert chosen(rb.RigidBody(J), "gpu", solver=diffrax.Kvaerno5()) is rb.Vmap
    assert type(default_batching(diffrax.Tsit5(), pid, None, backend="gpu")) is rb.Lanes
    # an error norm of the user's, which may not run on rows (this one indexes: a gather)
    own = eqx.tree_at(lambda c: c.norm, pid, lambda y: jnp.abs(y.omega[jnp.array([0, 2])]).max())
    assert (
        type(default_batching(diffrax.Tsit5(), own, None, rb.RigidBody(J), y0s, None, "gpu"))
        is rb.Lanes
    )


def test_a_default_device_on_a_cpu_takes_the_cpus_strategy(monkeypatch):
    """With JAX's backend a GPU (faked) but its default device a CPU (`jax.default_device`),
    a solve runs on the CPU, where Triton has no lowering: the default takes `Lanes`, and
    `Kernel()` its interpret mode, the same solve as asked for explicitly."""
    import rbdyn_jax.integrate._batching as batching

    y0s, model = initial_states(4), rb.RigidBody(J)
    pid = rb.integrate.make_controller(rtol=RTOL, atol=RTOL)
    kw = dict(rtol=RTOL, atol=RTOL)
    monkeypatch.setattr(batching.jax, "default_backend", lambda: "gpu")

    def default():
        return type(batching.default_batching(diffrax.Tsit5(), pid, None, model, y0s))

    assert default() is rb.Kernel
    for device in (jax.devices("cpu")[0], "cpu"):
        with jax.default_device(device):
            assert default() is rb.Lanes
            kernel = rb.simulate_batch(model, y0s, TS, batching=rb.Kernel(), **kw)
    asked = rb.simulate_batch(model, y0s, TS, batching=rb.Kernel(interpret=True), **kw)
    for x, y in zip(jax.tree_util.tree_leaves(kernel), jax.tree_util.tree_leaves(asked)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.core  # also under the next JAX: its Triton lowering changes
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_kernel_lowers_to_triton_for_a_gpu(dtype):
    """Exported for CUDA from this CPU (`jax.export`): every operation of the kernel body
    (rows of lanes, the loops, the gathered output times, the stores into each lane's
    column, the scalar reads of shared values) has a Triton lowering, and the kernel is a
    Triton call, not Mosaic GPU (JAX's default for `pallas_call` on a GPU), with a thread a
    lane: 64 lanes, 2 warps. `benchmarks/kernel_build.py` compiles such a module."""
    from rbdyn_jax.integrate._kernel_solve import kernel_solve

    y0s = initial_states(100, dtype=dtype)
    ts = np.linspace(0.0, 3.0, 7, dtype=dtype)
    model = rb.RigidBody(np.asarray(J, dtype), rb.GravityGradient(np.asarray(0.3, dtype)))
    pid = rb.integrate.make_controller(dtype=dtype)

    def solve(y0s, ts):
        return kernel_solve(model, y0s, ts, diffrax.Tsit5(), pid, 1000, None, None, 64, False)

    text = exported_for_cuda(solve, y0s, ts).mlir_module()
    assert "__gpu$xla.gpu.triton" in text and "mosaic" not in text.lower()
    assert "num_warps = 2 : i32" in text and "grid_x = 2 : i32" in text


def test_a_gpu_thread_a_lane():
    from rbdyn_jax.integrate._kernel_layout import triton_warps

    assert [triton_warps(b) for b in (1, 16, 32, 64, 128, 256, 1024, 4096)] == [
        1,
        1,
        1,
        2,
        4,
        8,
        32,
        32,
    ]


def exported_for_cuda(fn, *args):
    """`fn` exported for CUDA from this CPU (its checks as NaN: no host callback), its
    Triton calls allowed. Pallas's Triton lowering asks for the GPU's compute capability
    (from JAX 0.11): a machine without one names its target, an H100, by an abstract mesh."""
    from rbdyn_jax._program import checks

    mesh = jax.sharding.AbstractMesh(
        (1,),
        ("x",),
        (jax.sharding.AxisType.Explicit,),
        abstract_device=jax.sharding.AbstractDevice(
            device_kind="NVIDIA H100 80GB HBM3", num_cores=132, platform="gpu"
        ),
    )
    with checks.as_nan(), jax.sharding.use_abstract_mesh(mesh):
        return jax.export.export(
            jax.jit(fn),
            platforms=["cuda"],
            disabled_checks=[jax.export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")],
        )(*args)


GRAD_TS = jnp.linspace(0.0, 3.0, 3)
GRAD_RTOL = 1e-11


def _omega_loss(J, omega0, quat0, batching, solver=diffrax.Bosh3()):
    """Per trajectory, Σ sin ω over the saved times: a loss on ω alone."""
    tr = rb.simulate_batch(
        rb.RigidBody(J),
        rb.State(omega0, quat0),
        GRAD_TS,
        solver=solver,
        rtol=GRAD_RTOL,
        atol=GRAD_RTOL,
        batching=batching,
    )
    return jnp.sum(jnp.sin(tr.ys.omega), axis=(1, 2))


def test_gradients_and_jacobians_through_the_kernel():
    """`jax.grad` through the kernel w.r.t. the inertia and the initial rates: the forward
    sensitivities integrated in the kernel by the same steps, as the lane solver's, so the
    two agree to round-off (bound 1e-9 relative, as the lane solver's own gradient tests;
    the lanes' gradient is the sum over the trajectories of their `jax.jacfwd` of the
    per-trajectory losses). The loss reads ω alone, so the kernel integrates ω's sensitivities
    only (`_cheapest` chooses that program: ω's group of a free body). Against central
    differences of the kernel's own solve along a random direction (a symmetric δJ and a
    δω0): h = 1e-5 on O(1) inputs at rtol 1e-11 gives O(h²) + rtol/h ≈ 1e-6 relative
    error, bound 1e-5. The kernel's `jax.jacfwd` of the per-trajectory losses too, against
    the lanes'. Bosh3 and 4 trajectories."""
    from helpers import cheapest_call

    y0s = initial_states(4, seed=1)

    def loss(J, omega0, batching):
        return jnp.sum(_omega_loss(J, omega0, y0s.quat, batching))

    grad = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2, compiler_options=QUICK)
    traced = grad.trace(J, y0s.omega, rb.Kernel())
    call = cheapest_call(traced.jaxpr)
    carried = {k[1] for k in call.params["keys"][call.params["chosen"]] if k[0] == "S"}
    assert carried == {0}  # ω's sensitivities only
    gJ, gw = traced.lower().compile()(J, y0s.omega)

    # `jax.jacfwd` of the per-trajectory losses: the tangents share the one sensitivities'
    # solve. The lane solver's, summed over the trajectories, is its gradient (each loss
    # reads its own ω0 alone).
    def jac(batching):
        return jax.jit(
            jax.jacfwd(lambda J, w: _omega_loss(J, w, y0s.quat, batching), argnums=(0, 1)),
            compiler_options=QUICK,
        )(J, y0s.omega)

    lanes = jac(rb.Lanes())
    lJ, lw = (jnp.sum(x, axis=0) for x in lanes)
    scale = max(float(jnp.max(jnp.abs(lJ))), float(jnp.max(jnp.abs(lw))))
    assert scale > 1e-2  # a real gradient, not round-off
    for a, b in ((gJ, lJ), (gw, lw)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * scale)
    rng = np.random.default_rng(3)
    dJ = rng.normal(size=(3, 3))
    dJ = jnp.asarray(dJ + dJ.T)
    dw = jnp.asarray(rng.normal(size=y0s.omega.shape))
    f = jax.jit(lambda h: loss(J + h * dJ, y0s.omega + h * dw, rb.Kernel()), compiler_options=QUICK)
    h = 1e-5
    fd = (f(h) - f(-h)) / (2 * h)
    exact = jnp.sum(gJ * dJ) + jnp.sum(gw * dw)
    np.testing.assert_allclose(exact, fd, rtol=1e-5)

    # The kernel's `jax.jacfwd`: the lane solver's per trajectory, and summed over the
    # trajectories the gradient above (to round-off, as above).
    kernel = jac(rb.Kernel())
    assert kernel[0].shape == (4, 3, 3) and kernel[1].shape == (4, 4, 3)
    for k, l, g in zip(kernel, lanes, (gJ, gw)):
        jscale = float(jnp.max(jnp.abs(l)))
        assert jscale > 1e-2
        np.testing.assert_allclose(k, l, rtol=1e-9, atol=1e-12 * jscale)
        np.testing.assert_allclose(jnp.sum(k, axis=0), g, rtol=1e-9, atol=1e-12 * scale)


def test_gradients_for_per_trajectory_models_whole_states_and_times():
    """A heavy top per trajectory (its weight), a loss on the attitude and the rates:
    gravity couples ω̇ to q, so the kernel integrates the whole state's sensitivities, with
    each lane's own model. Gradients w.r.t. the weights, the initial states (ω0 and q0)
    and the output times equal the lane solver's to round-off (bound as above)."""
    y0s = initial_states(4, seed=2)
    weights = jnp.linspace(0.5, 2.0, 4)

    def loss(w, y0s, ts, batching):
        model = eqx.filter_vmap(heavy_top)(w)
        tr = rb.simulate_batch(
            model,
            y0s,
            ts,
            model_axes=0,
            solver=diffrax.Bosh3(),
            rtol=GRAD_RTOL,
            atol=GRAD_RTOL,
            batching=batching,
        )
        return jnp.sum(tr.ys.quat[..., 1:] ** 2) + jnp.sum(jnp.sin(tr.ys.omega))

    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3, compiler_options=QUICK)
    kernel = grad(weights, y0s, GRAD_TS, rb.Kernel())
    lanes = grad(weights, y0s, GRAD_TS, rb.Lanes())
    leaves = jax.tree_util.tree_leaves(lanes)
    scale = max(float(jnp.max(jnp.abs(x))) for x in leaves)
    assert min(float(jnp.max(jnp.abs(x))) for x in leaves) > 1e-2  # every one real
    for a, b in zip(jax.tree_util.tree_leaves(kernel), leaves):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * scale)


@pytest.mark.core
def test_the_gradient_kernel_lowers_to_triton_for_a_gpu():
    """`jax.grad` through the kernel, exported for CUDA from this CPU: the one kernel of
    the gradient program integrates the state and its sensitivities (a loss on ω and the
    attitude, six inertia parameters: 7 + 7 × 6 saved components) and lowers to Triton, every
    operation of the sensitivities' field (a `jax.jvp` of the model's, vmapped over the
    columns, on rows) included."""
    y0s, ts = initial_states(16), np.linspace(0.0, 3.0, 7)
    body = rb.RigidBody(J)

    ts = jnp.asarray(ts)  # a JAX array: closed over, as constants of the program

    def loss(theta):
        tr = rb.simulate_batch(
            rb.with_log_cholesky(body, theta),
            y0s,
            ts,
            batching=rb.Kernel(block=16, interpret=False, devices=1),
        )
        return jnp.sum(tr.ys.omega**2) + jnp.sum(tr.ys.quat[..., 1:] ** 2)

    text = exported_for_cuda(jax.grad(loss), rb.inertia.to_log_cholesky(J)).mlir_module()
    calls = [
        line
        for line in text.splitlines()
        if "custom_call" in line and "__gpu$xla.gpu.triton" in line
    ]
    assert len(calls) == 1 and "mosaic" not in text.lower()
    # Its outputs: the saved rows, 8 times (7 and a spare) × 64 components (7 + 7 × 6,
    # padded) × 16 lanes in one array, and the counts, 8 rows (5, padded) of 16 lanes.
    assert "-> (tensor<8192xf64>, tensor<128xi32>)" in calls[0]


def test_a_second_derivative_through_the_kernel_is_refused():
    y0s = initial_states(4)

    def loss(J):
        traj = rb.simulate_batch(rb.RigidBody(J), y0s, TS, batching=rb.Kernel())
        return jnp.sum(traj.ys.omega[:, -1])

    with pytest.raises(ValueError, match="not its derivative"):
        jax.jacfwd(jax.grad(loss))(J)


def test_euler_angle_and_poisson_forms():
    """The other state forms: their fields (and derivatives) run on rows as written
    (trigonometric kinematics; the Poisson vector γ)."""
    from rbdyn_jax.integrate._kernel_refusal import field_refuse

    rng = np.random.default_rng(1)
    omega = jnp.asarray(rng.normal(size=(6, 3)))
    angles = jnp.asarray(rng.uniform([0.0, 0.5, 0.0], [6.0, 2.5, 6.0], size=(6, 3)))
    gamma = jnp.asarray(rng.normal(size=(6, 3)))
    cases = [
        (rb.EulerAngleRigidBody(J, rb.RestoringMoment(1.0)), rb.EulerState(omega, angles)),
        (
            rb.PoissonRigidBody(J, rb.GravityGradient(0.3)),
            rb.PoissonState(omega, gamma / jnp.linalg.norm(gamma, axis=1, keepdims=True)),
        ),
    ]
    for model, y0s in cases:
        assert field_refuse(model, y0s, None) is None
        kw = dict(rtol=RTOL, atol=RTOL)
        kernel = rb.simulate_batch(model, y0s, TS, batching=rb.Kernel(), **kw)
        plain = rb.simulate_batch(model, y0s, TS, batching=rb.Vmap(), **kw)
        assert np.all(plain.result._value == 0)
        assert_same_solves(kernel, plain)


# --------------------------------------------------------------------------------------
# Sweeps: the default's batching
# --------------------------------------------------------------------------------------

SWEEP_N = 12


def test_a_sweep_on_a_gpu_takes_the_kernel(monkeypatch, tmp_path):
    """On a GPU backend (faked: JAX's backend reported as a GPU, the kernel in interpret
    mode since the CPU has no Triton, and each chunk's device share solved in one block as
    on a GPU) a sweep takes the default's `Kernel`, on each device's share. Its store is
    the same to the bit for two chunkings (each trajectory is integrated in its own lane,
    whatever the others are), and equals the lane solver's store to round-off: the same
    step counts and codes, values within `ROUND_OFF` (the unrolled stages and the rows'
    sums round differently in the last bits; states and summaries of size ≲ 3 here;
    measured ≤ 2.2e-14)."""
    from helpers import load_store, small_scenario

    import rbdyn_jax.integrate._batching as batching
    from rbdyn_jax import sweep
    from rbdyn_jax.scenario import Scenario

    sc = Scenario.from_dict(small_scenario(time={"t1": 2.0, "n": 5}))
    chosen = []
    real = sweep._chunk._batching

    def recorded(*args):
        out = real(*args)
        chosen.append(out)
        return out

    def run(name, chunk):
        return load_store(sweep.run(sc, SWEEP_N, tmp_path / name, chunk=chunk, seed=3, lanes=4))

    monkeypatch.setattr(sweep._chunk, "_batching", recorded)
    lanes = run("lanes.zarr", SWEEP_N)
    assert {type(b) for b in chosen} == {rb.Lanes}
    chosen.clear()
    monkeypatch.setattr(batching, "Kernel", lambda: rb.Kernel(interpret=True))
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(sweep._chunk, "_quantum", lambda platform, lanes: 1)
    jax.clear_caches()  # the chunk program compiled for the CPU's choice
    one = run("k12.zarr", SWEEP_N)
    split = run("k5.zarr", 5)
    # inside the chunk's program over the devices: each device's share on its device
    assert {(type(b), b.devices) for b in chosen} == {(rb.Kernel, 1)}
    for k in one:
        np.testing.assert_array_equal(one[k], split[k], err_msg=k)
    assert np.all(one["status"] == 0)
    for k in ("status", "num_steps", "inertia"):
        np.testing.assert_array_equal(one[k], lanes[k], err_msg=k)
    for k in ("omega", "quat", "energy_drift", "max_abs_omega", "first_flip_time"):
        np.testing.assert_allclose(
            one[k], lanes[k], rtol=0, atol=ROUND_OFF, equal_nan=True, err_msg=k
        )
