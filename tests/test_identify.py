"""rbdyn_jax.identify: observations, losses, `fit` and its uncertainty.

- recover a general inertia (products of inertia) from noisy synthetic ω and attitude
  records of 3 bodies under uniform gravity (a known torque), initial states free: error
  within a few standard errors, every iterate physical, converged; a small coverage check
  over noise seeds (the same compiled fit is reused: values change, structure does not);
- the batched loss's gradient against central finite differences;
- torque-free data: the scale of J is detected as undetermined without a scale fix, and fixed
  by `scale=TraceScale(value)` or `scale=MomentScale(axis, value)`; the scale classes check
  their arguments, and a tuple `scale` is refused;
- the optimisers: `LevenbergMarquardt` (the default) and `Optax(tx)` (here L-BFGS), their
  fields checked, a bare optax transformation refused;
- step-size control: `stepsize_controller=PIDController(r, a)` is the same fit as
  `rtol=r, atol=a`, and a new tolerance reuses the compiled fit;
- bad data: NaN samples, non-increasing times, mismatched shapes, non-unit quaternions.

Compilation dominates the run time: one fit structure per scenario, small records.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb
from rbdyn_jax import identify as idf
from rbdyn_jax.identify import _problem

_R = Rotation.from_euler("ZYX", [0.4, -0.3, 0.7]).as_matrix()
J_TRUE = _R @ np.diag([2.0, 3.0, 4.0]) @ _R.T
J_TRUE = 0.5 * (J_TRUE + J_TRUE.T)
GRAVITY = rb.UniformGravity(1.5, jnp.array([0.1, -0.05, 0.3]))
TS = np.linspace(0.0, 4.0, 21)
W0 = np.array([[0.4, -1.1, 0.7], [1.0, 0.3, -0.5], [-0.2, 0.8, 1.2]])
Q0 = Rotation.from_euler("ZXZ", [[1.0, 0.6, 0.2], [0.3, 1.2, -0.5], [-1.0, 0.9, 2.0]]).as_quat(
    scalar_first=True
)
SIGMA_W, SIGMA_Q = 0.01, 0.005
J_GUESS = np.diag(np.diag(J_TRUE)) * 1.1  # no products of inertia, moments 10% off
LM12, LM20 = idf.LevenbergMarquardt(steps=12), idf.LevenbergMarquardt(steps=20)
UPPER = np.triu_indices(3)


def truth(model, w0=W0, q0=Q0, ts=TS):
    traj = rb.simulate_batch(
        model, rb.State(jnp.asarray(w0), jnp.asarray(q0)), ts, rtol=1e-12, atol=1e-12, throw=True
    )
    return np.asarray(traj.ys.omega), np.asarray(traj.ys.quat)


def noisy(omega, quat, seed, ts=TS):
    rng = np.random.default_rng(seed)
    w = omega + SIGMA_W * rng.standard_normal(omega.shape)
    dq = rb.rotation.quat_from_rotvec(jnp.asarray(SIGMA_Q * rng.standard_normal(omega.shape)))
    q = np.asarray(rb.rotation.quat_multiply(jnp.asarray(quat), dq))
    q = np.where(rng.random(q.shape[:-1] + (1,)) < 0.5, -q, q)  # the sign is irrelevant
    return idf.Observations(ts, omega=w, quat=q, sigma_omega=SIGMA_W, sigma_quat=SIGMA_Q)


# The tests reading a module's shared truth (and the fit of the gravity data) share one
# worker (`--dist loadgroup`): each is computed once, and the fits they compile are reused.
@pytest.fixture(scope="module")
def gravity_truth():
    return truth(rb.RigidBody(jnp.asarray(J_TRUE), GRAVITY))


def fit_gravity(data):
    return idf.fit(rb.RigidBody(jnp.asarray(J_GUESS), GRAVITY), data, optimizer=LM12)


@pytest.fixture(scope="module")
def gravity_fit(gravity_truth):
    return fit_gravity(noisy(*gravity_truth, seed=0))


def z_scores(res):
    err = np.asarray(res.model.inertia) - J_TRUE
    return (err / np.asarray(res.stderr["inertia"]))[UPPER]


@pytest.mark.xdist_group("identify_gravity")
def test_recover_inertia_with_products(gravity_fit):
    res = gravity_fit
    assert res.converged and res.scale_identified and res.ill_determined == 0
    z = z_scores(res)
    # 6 independent-ish components; |z| < 3.5 each (measured max 0.91 for seed 0).
    assert np.all(np.abs(z) < 3.5), z
    # Standard errors are small against the products of inertia (~0.3–0.6): informative.
    assert np.max(np.asarray(res.stderr["inertia"])) < 0.05
    # χ² at the optimum ≈ number of residuals − number of parameters (378 − 24).
    dof = 3 * 21 * 6 - res.covariance.shape[0]
    assert abs(2 * float(res.loss) - dof) < 5 * np.sqrt(2 * dof)
    assert res.stderr["omega0"].shape == (3, 3) and res.stderr["quat0"].shape == (3, 3)
    assert len(res.labels) == res.covariance.shape[0]


@pytest.mark.xdist_group("identify_gravity")
def test_every_iterate_is_physical(gravity_fit):
    Js = gravity_fit.inertia_history
    assert Js.shape == (13, 3, 3)
    assert bool(jnp.all(rb.inertia.is_physical(Js)))
    hist = np.asarray(gravity_fit.loss_history)
    assert np.all(np.diff(hist) <= 0)  # LM accepts only decreasing steps
    assert hist[-1] < 2e-3 * hist[0]  # from ~1.8e5 down to the noise floor χ²/2 ≈ 180


@pytest.mark.xdist_group("identify_gravity")
def test_coverage_over_noise_seeds(gravity_truth):
    # Same structure and sizes: the compiled fit is reused (~0.5 s per fit).
    z = np.concatenate([z_scores(fit_gravity(noisy(*gravity_truth, seed=s))) for s in range(1, 7)])
    # Mean of z² over 36 components (correlated within a fit): 1 if the stderr are right.
    # Bounds catch a factor ~2 misestimate of the stderr in either direction.
    assert 0.25 < np.mean(z**2) < 3.0, z
    assert np.mean(np.abs(z) < 2.0) > 0.75


@pytest.mark.xdist_group("identify_gravity")
def test_batched_loss_gradient_matches_finite_differences(gravity_truth):
    data = noisy(*gravity_truth, seed=0)
    y0s = rb.State(jnp.asarray(W0), jnp.asarray(Q0))

    @eqx.filter_jit
    def loss_of(theta, omega0):
        model = rb.RigidBody(rb.inertia.from_log_cholesky(theta), GRAVITY)
        return idf.loss(model, rb.State(omega0, y0s.quat), data, rtol=1e-12, atol=1e-12)

    theta = rb.inertia.to_log_cholesky(jnp.asarray(J_GUESS + 0.05))
    g_theta, g_w = jax.grad(loss_of, argnums=(0, 1))(theta, y0s.omega)
    x = np.concatenate([np.asarray(theta), np.asarray(y0s.omega).ravel()])
    g = np.concatenate([np.asarray(g_theta), np.asarray(g_w).ravel()])
    h = 1e-5
    fd = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        fp, fm = x + e, x - e
        plus = loss_of(jnp.asarray(fp[:6]), jnp.asarray(fp[6:].reshape(3, 3)))
        minus = loss_of(jnp.asarray(fm[:6]), jnp.asarray(fm[6:].reshape(3, 3)))
        fd.append((float(plus) - float(minus)) / (2 * h))
    fd = np.array(fd)
    # Loss ~1e5 with gradients ~1e5–1e6: FD truncation h² ~ 1e-10 relative, solve noise
    # ~1e-12 × loss / h ~ 1e-2 absolute.
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.linalg.norm(fd))


@pytest.fixture(scope="module")
def free_truth():
    return truth(rb.RigidBody(jnp.asarray(J_TRUE)))


@pytest.mark.xdist_group("identify_free")
def test_torque_free_scale_detected_and_fixed(free_truth):
    data = noisy(*free_truth, seed=3)
    guess = rb.RigidBody(jnp.asarray(J_GUESS))
    res = idf.fit(guess, data, optimizer=LM12)
    assert not res.scale_identified
    assert any("up to scale" in n for n in res.notes)
    assert np.all(np.isinf(np.asarray(res.stderr["inertia"])))
    # The shape of J is still recovered: J / tr J.
    J = np.asarray(res.model.inertia)
    np.testing.assert_allclose(J / np.trace(J), J_TRUE / np.trace(J_TRUE), atol=0.02)

    trace = float(np.trace(J_TRUE))
    fixed = idf.fit(guess, data, optimizer=LM12, scale=idf.TraceScale(trace))
    assert fixed.scale_identified and fixed.converged
    assert any("fixed by the user" in n for n in fixed.notes)
    Jf = np.asarray(fixed.model.inertia)
    np.testing.assert_allclose(np.trace(Jf), trace, rtol=1e-12)
    se = np.asarray(fixed.stderr["inertia"])
    assert np.all(np.isfinite(se)) and np.max(se) < 0.2
    z = ((Jf - J_TRUE) / se)[UPPER]
    assert np.all(np.abs(z) < 4.0), z
    assert bool(jnp.all(rb.inertia.is_physical(fixed.inertia_history)))

    # The same optimum with the scale fixed by a moment about a non-principal axis instead:
    # nᵀ J n held at the trace fit's value gives the trace fit's J.
    n = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    by_moment = idf.fit(guess, data, optimizer=LM12, scale=idf.MomentScale((1, 1, 0), n @ Jf @ n))
    assert by_moment.scale_identified and by_moment.converged
    assert any("fixed by the user: nᵀ J n" in note for note in by_moment.notes)
    Jm = np.asarray(by_moment.model.inertia)
    np.testing.assert_allclose(n @ Jm @ n, n @ Jf @ n, rtol=1e-12)
    np.testing.assert_allclose(Jm, Jf, atol=1e-6 * np.max(se))


@pytest.mark.xdist_group("identify_free")
def test_scale_value_and_damping_are_inputs_of_the_compiled_fit(free_truth, monkeypatch):
    """A new `TraceScale` value or Levenberg–Marquardt `damping` reuses the compiled fit
    (the fit is not traced again), and the new values reach it: its loss history is that of
    a fit traced with them (`steps` differs, so it is traced anew), to round-off; and with
    no torque the data fix J only up to scale, so doubling the trace held doubles the
    fitted J (to the optimiser's convergence, 1e-6 of the trace)."""
    data = noisy(*free_truth, seed=3)
    guess = rb.RigidBody(jnp.asarray(J_GUESS))
    trace = float(np.trace(J_TRUE))
    first = idf.fit(guess, data, optimizer=LM12, scale=idf.TraceScale(trace))
    doubled = idf.TraceScale(2 * trace)
    fresh = idf.fit(guess, data, optimizer=idf.LevenbergMarquardt(13, damping=0.1), scale=doubled)
    traced = []
    residuals = idf.residuals
    monkeypatch.setattr(
        _problem, "residuals", lambda *a, **k: traced.append(1) or residuals(*a, **k)
    )
    reused = idf.fit(guess, data, optimizer=idf.LevenbergMarquardt(12, damping=0.1), scale=doubled)
    assert not traced
    np.testing.assert_allclose(reused.loss_history, fresh.loss_history[:13], rtol=1e-9)
    # λ = 0.1 and λ = 1e-3 take different first steps (loss 4.6e4 and 6.7e4 after them).
    assert abs(float(reused.loss_history[1]) / float(first.loss_history[1]) - 1) > 0.1
    assert first.converged and reused.converged
    J1, J2 = np.asarray(first.model.inertia), np.asarray(reused.model.inertia)
    np.testing.assert_allclose(np.trace(J2), 2 * trace, rtol=1e-12)
    np.testing.assert_allclose(J2, 2 * J1, atol=1e-6 * trace)


@pytest.mark.xdist_group("identify_free")
def test_a_fit_none_of_whose_solves_succeeds_is_not_converged(free_truth):
    """Every solve runs out of steps (at the guess too): no point was accepted, so the fit
    reports no loss (NaN), is not converged, says why, and returns the guess (at the
    fixed scale)."""
    guess = rb.RigidBody(jnp.asarray(J_GUESS))
    res = idf.fit(
        guess,
        noisy(*free_truth, seed=3),
        optimizer=idf.LevenbergMarquardt(steps=3),
        scale=idf.TraceScale(float(np.trace(J_TRUE))),
        max_steps=5,
    )
    assert not res.converged and not np.isfinite(float(res.loss))
    assert any(n.startswith("No solve succeeded") for n in res.notes), res.notes
    assert not np.any(np.isfinite(np.asarray(res.loss_history)))
    J = np.asarray(res.model.inertia)  # the guess, at the scale fixed
    np.testing.assert_allclose(J / np.trace(J), J_GUESS / np.trace(J_GUESS), rtol=1e-12)


def test_scale_classes():
    J = jnp.asarray(J_TRUE)
    for scale in (idf.TraceScale(9), idf.MomentScale(2, 1.0)):
        assert isinstance(scale, idf.AbstractScale)
        np.testing.assert_allclose(scale.of(scale.rescale(J)), scale.value, rtol=1e-14)
    with pytest.raises(TypeError):
        idf.AbstractScale()
    assert float(idf.TraceScale(9).of(J)) == pytest.approx(np.trace(J_TRUE))
    assert float(idf.MomentScale(2, 1.0).of(J)) == pytest.approx(J_TRUE[2, 2])
    n = np.array([3.0, 0.0, 4.0]) / 5.0
    assert float(idf.MomentScale([3, 0, 4], 1.0).of(J)) == pytest.approx(n @ J_TRUE @ n)
    assert idf.MomentScale(np.int64(1), 2).axis == 1  # a NumPy index is an index
    for value in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="TraceScale: `value` must be finite and positive"):
            idf.TraceScale(value)
        with pytest.raises(ValueError, match="MomentScale: `value` must be finite and positive"):
            idf.MomentScale(0, value)
    with pytest.raises(ValueError, match="`axis` index must be 0, 1 or 2"):
        idf.MomentScale(3, 1.0)
    for axis in ((0, 0, 0), (1, 2), np.eye(3), 1.0, True, "x", (1.0, np.nan, 0.0)):
        with pytest.raises(ValueError, match="`axis` must be an index 0, 1 or 2 or a non-zero"):
            idf.MomentScale(axis, 1.0)


# ---------------------------------------------------------------------------------------
# Bad data.

W_OK = np.zeros((2, 5, 3))
Q_OK = np.tile([1.0, 0.0, 0.0, 0.0], (2, 5, 1))
T_OK = np.linspace(0.0, 1.0, 5)


def test_nan_sample_raises_or_is_masked():
    w = W_OK.copy()
    w[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="`omega` has a non-finite sample.*trajectory 1"):
        idf.Observations(T_OK, omega=w, quat=Q_OK)
    data = idf.Observations(T_OK, omega=w, quat=Q_OK, nan_policy="mask")
    assert not bool(data.mask_omega[1, 2]) and bool(data.mask_quat[1, 2])
    assert bool(jnp.all(jnp.isfinite(data.omega)))


def test_non_increasing_times():
    t = T_OK.copy()
    t[3] = t[2]
    with pytest.raises(ValueError, match="`ts` must be strictly increasing"):
        idf.Observations(t, omega=W_OK)


def test_mismatched_shapes():
    with pytest.raises(ValueError, match="`quat` must have shape"):
        idf.Observations(T_OK, omega=W_OK, quat=Q_OK[:, :4])
    with pytest.raises(ValueError, match="`ts` must have shape"):
        idf.Observations(T_OK[:4], omega=W_OK)
    with pytest.raises(ValueError, match="`sigma_omega`"):
        idf.Observations(T_OK, omega=W_OK, sigma_omega=np.ones(4))
    with pytest.raises(ValueError, match="at least one"):
        idf.Observations(T_OK)
    with pytest.raises(ValueError, match="`omega` must be real, got dtype complex128"):
        idf.Observations(T_OK, omega=W_OK + 1e-3j)  # not cast, dropping the imaginary part


def test_non_unit_quaternion():
    q = Q_OK.copy()
    q[0, 1] *= 1.1
    with pytest.raises(ValueError, match="`quat` is not a unit quaternion.*trajectory 0, sample 1"):
        idf.Observations(T_OK, quat=q)
    data = idf.Observations(T_OK, quat=q, normalize_quat=True)
    np.testing.assert_allclose(np.linalg.norm(data.quat, axis=-1), 1.0, rtol=1e-15)
    q[0, 1] = 0.0
    with pytest.raises(ValueError, match="not a unit quaternion"):
        idf.Observations(T_OK, quat=q, normalize_quat=True)


def test_padding_of_different_lengths():
    mask = np.ones((2, 5), bool)
    mask[1, 3:] = False
    t = np.tile(T_OK, (2, 1))
    t[1, 3:] = np.nan  # padding: times ignored
    w = W_OK.copy()
    w[1, 3:] = np.nan
    data = idf.Observations(t, omega=w, mask=mask)
    ts = np.asarray(data.ts)
    assert np.all(np.diff(ts, axis=1) > 0) and ts[1, 2] == T_OK[2]
    assert not bool(jnp.any(data.mask_omega[1, 3:]))


def test_fit_argument_errors():
    data = idf.Observations(T_OK, omega=W_OK)
    model = rb.RigidBody(jnp.asarray(J_TRUE))
    with pytest.raises(ValueError, match="`params`"):
        idf.fit(model, data, params=("mass",))
    with pytest.raises(ValueError, match="got 'mass'"):  # a name, not its letters
        idf.fit(model, data, params="mass")
    for rcond in (-1.0, 0.0, 1.0, "1e-9"):
        with pytest.raises(ValueError, match="`rcond`"):
            idf.fit(model, data, rcond=rcond)
    with pytest.raises(ValueError, match=r"`y0` must be a State\(omega, quat\), got tuple"):
        idf.fit(model, data, y0=(W_OK[:1, 0], np.array([[1.0, 0, 0, 0]])))
    for scale in (("trace", 1.0), ("moment", 0, 1.0), 1.0):
        with pytest.raises(
            ValueError,
            match=r"`scale` must be None, identify.TraceScale\(value\) "
            r"or identify.MomentScale\(axis, value\)",
        ):
            idf.fit(model, data, scale=scale)
    controller = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    for tols in ({"rtol": 1e-8}, {"atol": 1e-8}):
        with pytest.raises(ValueError, match="not both"):
            idf.fit(model, data, stepsize_controller=controller, **tols)
    with pytest.raises(ValueError, match="`rtol` must be a positive scalar"):
        idf.fit(model, data, rtol=-1e-8)
    with pytest.raises(ValueError, match="'torque'"):
        idf.fit(model, data, params=("torque",))
    import optax

    for optimizer in (optax.adam(1e-2), None, "lm"):
        with pytest.raises(
            ValueError,
            match=r"`optimizer` must be identify.LevenbergMarquardt"
            r"\(...\) or identify.Optax\(tx, ...\)",
        ):
            idf.fit(model, data, optimizer=optimizer)


def test_optimizer_classes():
    """The optimisers' defaults and the checks of their fields; both are
    `AbstractOptimizer`s, and `fit`'s default is Levenberg–Marquardt."""
    import inspect

    import optax

    lm = idf.LevenbergMarquardt()
    assert (lm.steps, lm.tol, lm.damping) == (30, 1e-6, 1e-3)
    assert inspect.signature(idf.fit).parameters["optimizer"].default == lm
    tx = optax.adam(1e-2)
    adam = idf.Optax(tx, steps=np.int64(5))
    assert adam.tx is tx and (adam.steps, adam.tol) == (5, 1e-6) and type(adam.steps) is int
    assert all(isinstance(o, idf.AbstractOptimizer) for o in (lm, adam))
    for cls, args in ((idf.LevenbergMarquardt, ()), (idf.Optax, (tx,))):
        name = cls.__name__
        for steps in (0, -1, 2.5, True):
            with pytest.raises(ValueError, match=f"{name}: `steps` must be a positive int"):
                cls(*args, steps=steps)
        for tol in (-1e-3, np.nan):
            with pytest.raises(ValueError, match=f"{name}: `tol` must be ≥ 0"):
                cls(*args, tol=tol)
    for damping in (0.0, -1.0, np.inf):
        with pytest.raises(ValueError, match="`damping` must be finite and positive"):
            idf.LevenbergMarquardt(damping=damping)
    with pytest.raises(ValueError, match="Optax: `tx` must be an optax GradientTransformation"):
        idf.Optax(lambda g: g)
    with pytest.raises(TypeError):
        idf.AbstractOptimizer()


@pytest.mark.xdist_group("identify_gravity")
def test_stepsize_controller_is_the_tolerance_shorthand(gravity_truth, monkeypatch):
    """`stepsize_controller=PIDController(rtol=r, atol=a)` is the fit `rtol=r, atol=a` gives,
    bitwise. The tolerances are inputs of the compiled fit: a fit at other tolerances reuses
    it (the fit is not traced again)."""
    data = noisy(*gravity_truth, seed=0)
    guess = rb.RigidBody(jnp.asarray(J_GUESS), GRAVITY)
    by_tol = idf.fit(guess, data, optimizer=LM12, rtol=1e-9, atol=1e-11)
    traced = []
    residuals = idf.residuals
    monkeypatch.setattr(
        _problem, "residuals", lambda *a, **k: traced.append(1) or residuals(*a, **k)
    )
    controller = diffrax.PIDController(rtol=3e-9, atol=3e-11)
    idf.fit(guess, data, optimizer=LM12, stepsize_controller=controller)
    by_controller = idf.fit(
        guess,
        data,
        optimizer=LM12,
        stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-11),
    )
    assert not traced
    np.testing.assert_array_equal(by_controller.model.inertia, by_tol.model.inertia)
    np.testing.assert_array_equal(by_controller.loss_history, by_tol.loss_history)
    np.testing.assert_array_equal(by_controller.covariance, by_tol.covariance)


@pytest.mark.xdist_group("identify_gravity")
def test_optax_optimizer_path_descends_and_stays_physical(gravity_truth):
    """`optimizer=` runs any optax transformation (here L-BFGS) inside the compiled fit:
    the loss falls by over 10× in 20 steps (measured 178k → 1.6k from a 10 %-off diagonal
    guess) and every iterate's inertia is physical (log-Cholesky parametrisation)."""
    import optax

    data = noisy(*gravity_truth, seed=0)
    # optax's L-BFGS mixes int32/int64 internally: strict promotion is relaxed for it only.
    with jax.numpy_dtype_promotion("standard"):
        res = idf.fit(
            rb.RigidBody(jnp.asarray(J_GUESS), GRAVITY),
            data,
            optimizer=idf.Optax(optax.lbfgs(), steps=20),
        )
    lh = np.asarray(res.loss_history)
    assert np.all(np.isfinite(lh)) and lh[-1] < lh[0] / 10
    assert np.all(np.asarray(rb.inertia.is_physical(res.model.inertia)))


@pytest.mark.xdist_group("identify_gravity")
def test_euler_angle_observations_equal_quaternion_ones(gravity_truth):
    """Attitude given as ZXZ angles (scipy's conversion of the true quaternions) gives the
    same observations and the same loss as the quaternions themselves."""
    w, q = gravity_truth
    angles = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_euler("ZXZ")
    angles = angles.reshape(q.shape[:-1] + (3,))
    by_q = idf.Observations(TS, omega=w, quat=q, sigma_omega=SIGMA_W, sigma_quat=SIGMA_Q)
    by_e = idf.Observations(
        TS, omega=w, euler=angles, seq="ZXZ", sigma_omega=SIGMA_W, sigma_quat=SIGMA_Q
    )
    by_deg = idf.Observations(TS, omega=w, euler=np.degrees(angles), degrees=True)
    sign = np.sign(np.sum(np.asarray(by_e.quat) * q, axis=-1, keepdims=True))
    np.testing.assert_allclose(sign * np.asarray(by_e.quat), q, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(by_deg.quat) * q, -1)), 1.0, atol=1e-12)
    model = rb.RigidBody(jnp.asarray(J_GUESS), GRAVITY)
    y0s = rb.State(jnp.asarray(W0), jnp.asarray(Q0))
    np.testing.assert_allclose(idf.loss(model, y0s, by_e), idf.loss(model, y0s, by_q), rtol=1e-9)
    with pytest.raises(ValueError, match="not both"):
        idf.Observations(TS, quat=q, euler=angles)
    with pytest.raises(ValueError, match="`euler` must have shape"):
        idf.Observations(TS, euler=angles[..., :2])


def test_a_stage_holds_its_fraction_of_the_record_wherever_the_record_lies():
    """A staged fit's stage holds the samples up to its fraction of each trajectory's
    recorded span, the same ones for a record at negative or large times as at [0, 4],
    and the last stage (1) every recorded sample, the last included."""
    from rbdyn_jax.identify._fit import stage_samples

    ts = np.stack([np.linspace(0.0, 4.0, 41)] * 2)
    mask = np.ones(ts.shape, bool)
    mask[1, :3] = mask[1, -2:] = False  # the second record spans [0.3, 3.8]
    for frac, counts in ((0.25, (11, 9)), (0.5, (21, 18)), (1.0, (41, 36))):
        ref = stage_samples(ts, mask, frac)
        assert tuple(np.sum(ref & mask, axis=1)) == counts
        for shift in (-5.0, -1e3, 7.0):
            np.testing.assert_array_equal(stage_samples(ts + shift, mask, frac), ref)


def test_staged_horizons_rescue_a_long_record():
    """Over t ∈ [0, 40] the heavy top's record is long enough that a fit from a 30 %-off
    diagonal guess stalls in a local minimum (measured χ²/dof ≈ 330). Staged horizons
    (10 %, 25 %, 50 %, 100 % of the record) reach the noise floor (χ²/dof ≈ 1) with the
    inertia within a few standard errors, and every stage reuses the one compilation."""
    ts = np.linspace(0.0, 40.0, 61)
    data = noisy(
        *truth(rb.RigidBody(jnp.asarray(J_TRUE), GRAVITY), w0=W0[:2], q0=Q0[:2], ts=ts),
        seed=0,
        ts=ts,
    )
    guess = rb.RigidBody(jnp.asarray(np.diag(np.diag(J_TRUE)) * 1.3), GRAVITY)
    dof = 2 * 61 * 6 - (6 + 12)
    direct = idf.fit(guess, data, optimizer=LM20)
    assert 2 * float(direct.loss) / dof > 10 and not direct.converged
    staged = idf.fit(guess, data, optimizer=LM20, horizons=(0.1, 0.25, 0.5, 1.0))
    assert staged.converged and 2 * float(staged.loss) / dof < 1.3
    z = (np.asarray(staged.model.inertia) - J_TRUE) / np.asarray(staged.stderr["inertia"])
    assert np.max(np.abs(z[UPPER])) < 4.0
    assert any("Staged horizons" in n for n in staged.notes)
    with pytest.raises(ValueError, match="`horizons`"):
        idf.fit(guess, data, horizons=(0.5, 0.2, 1.0))
