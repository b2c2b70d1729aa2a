"""Torques (`rbdyn_jax.torques`) against the hand formulas of the physics guide.

References that cannot be wrong in the same way as the library:

- torques: the hand formulas of docs/physics.md in NumPy, with attitudes, Euler angles and
  axis directions from `scipy.spatial.transform.Rotation`, on the kinematics record of a
  relative model (`helpers.relative_setup`, the record itself checked in test_models.py);
- parameter gradients: central finite differences of every parameter leaf and of J;
- potentials: central finite differences of V along explicit rotation paths built with scipy
  (−dV/dt = ω·M), and `jax.jvp` along the hand quaternion kinematics.

Finite differences use central steps h with truncation error ~h²·|f'''| and rounding
~1e-16/h (h = 1e-5 ⇒ both ≲ 1e-10).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    FD_H,
    FD_TOL,
    TIGHT,
    general_inertia,
    random_quat,
    relative_setup,
    scipy_rot,
    xyzw_to_wxyz,
    zxz,
)
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb


@pytest.fixture
def rel_setup(rng):
    """A relative model under a time-varying ZXZ frame, a random state and time, with every
    quantity a torque sees recomputed independently (`helpers.relative_setup`)."""
    return relative_setup(rng)


# ------------------------------------------------------------------------------------------
# Torques at the unit level (vs NumPy hand formulas with scipy attitudes)
# ------------------------------------------------------------------------------------------


def test_body_and_inertial_torques(rel_setup, rng):
    model, kin, ref = rel_setup
    J = jnp.asarray(ref["J"])
    M = rng.normal(size=3)
    np.testing.assert_allclose(rb.BodyTorque(M)(kin, J), M, atol=TIGHT)
    # A moment fixed in O0: body components R(q_abs)ᵀ M0, q_abs = q_e ⊗ q_r (scipy).
    np.testing.assert_allclose(rb.InertialTorque(M)(kin, J), ref["Ra"].inv().apply(M), atol=TIGHT)
    np.testing.assert_allclose(rb.NoTorque()(kin, J), 0.0, atol=0)


def test_uniform_gravity(rel_setup, rng):
    model, kin, ref = rel_setup
    J = jnp.asarray(ref["J"])
    mg, r_c = 2.3, rng.normal(size=3)
    # M = r_c × (−mg γ₀) with γ₀ the inertial z0-axis in body components (scipy).
    np.testing.assert_allclose(
        rb.UniformGravity(mg, r_c)(kin, J), np.cross(r_c, -mg * ref["gamma0"]), atol=TIGHT
    )


def test_uniform_gravity_is_the_lagrange_top_moment(rng):
    """docs/physics.md#equations-of-motion: com = (0, 0, l) ⇒ M = k sinθ (cos φ, −sin φ, 0), k =
    m g l, with (ψ, θ, φ) the ZXZ angles of the body from scipy."""
    mg, l = 1.7, 0.4
    model = rb.RigidBody(
        jnp.diag(jnp.array([1.0, 1.0, 1.5])), rb.UniformGravity(mg, jnp.array([0.0, 0.0, l]))
    )
    for _ in range(5):
        q = random_quat(rng)
        kin = model.kinematics(
            jnp.asarray(0.0), rb.State(jnp.asarray(rng.normal(size=3)), jnp.asarray(q))
        )
        _, th, ph = zxz(q)
        ref = mg * l * np.sin(th) * np.array([np.cos(ph), -np.sin(ph), 0.0])
        np.testing.assert_allclose(model.torque(kin, model.inertia), ref, atol=TIGHT)


def test_restoring_moment_constant_and_polynomial_sin_psi(rel_setup):
    """docs/physics.md#equations-of-motion: M = k(τ, ψ) sinθ (cos φ, −sin φ, 0) with
    (ψ, θ, φ) the ZXZ angles of the body relative to its parent frame, and
    k = ε K(τ) sin ψ, τ = ε t."""
    model, kin, ref = rel_setup
    J = jnp.asarray(ref["J"])
    psi, th, ph = zxz(ref["q_r"])
    lever = np.sin(th) * np.array([np.cos(ph), -np.sin(ph), 0.0])
    np.testing.assert_allclose(rb.RestoringMoment(0.8)(kin, J), 0.8 * lever, atol=TIGHT)

    coeffs, eps = np.array([0.7, -0.4, 0.25]), 0.3
    tau = eps * ref["t"]
    k = eps * (coeffs[0] + coeffs[1] * tau + coeffs[2] * tau**2) * np.sin(psi)
    torque = rb.RestoringMoment(rb.PolynomialSinPsi(coeffs, eps), eps=eps)
    np.testing.assert_allclose(torque(kin, J), k * lever, atol=TIGHT)


def test_gravity_gradient(rel_setup):
    """docs/physics.md#torque-and-integrals: M = ε γ × J γ, γ = parent z-axis in body
    components; ε = 3 n²."""
    model, kin, ref = rel_setup
    J = ref["J"]
    g = ref["gamma"]
    np.testing.assert_allclose(
        rb.GravityGradient(1.7)(kin, jnp.asarray(J)), 1.7 * np.cross(g, J @ g), atol=TIGHT
    )
    n = 0.37
    np.testing.assert_allclose(rb.GravityGradient.from_orbit_rate(n).eps, 3 * n * n, rtol=TIGHT)


def test_balancing_transport(rel_setup):
    """docs/physics.md#balancing-transport-moment: M = J ε_e − J ω_e × ω_e, with ω_e, ε_e
    of the frame (hand formula)."""
    model, kin, ref = rel_setup
    J, w_e, e_e = ref["J"], ref["w_e"], ref["e_e"]
    np.testing.assert_allclose(
        rb.BalancingTransport()(kin, jnp.asarray(J)),
        J @ e_e - np.cross(J @ w_e, w_e),
        atol=10 * FD_TOL,
    )


def test_sum_torque_adds_and_flattens(rel_setup, rng):
    model, kin, ref = rel_setup
    J = jnp.asarray(ref["J"])
    a = rb.BodyTorque(rng.normal(size=3))
    b = rb.UniformGravity(1.1, rng.normal(size=3))
    c = rb.GravityGradient(0.9)
    total = a + b + c
    assert isinstance(total, rb.SumTorque) and len(total.torques) == 3
    expected = np.asarray(a(kin, J)) + np.asarray(b(kin, J)) + np.asarray(c(kin, J))
    np.testing.assert_allclose(total(kin, J), expected, atol=TIGHT)
    np.testing.assert_allclose(rb.SumTorque(a, b + c)(kin, J), expected, atol=TIGHT)


def _fd_gradient_check(torque, kin, J, c, h=1e-6):
    """jax.grad of c·M(params, J) w.r.t. every parameter leaf and J vs central FD.

    h = 1e-6: truncation ~1e-12·|f'''|, rounding ~1e-16/1e-6 = 1e-10 ⇒ agreement to 1e-7.
    """

    def f(params, J):
        return jnp.dot(c, eqx.combine(params, static)(kin, J))

    params, static = eqx.partition(torque, eqx.is_inexact_array)
    g_params, g_J = jax.grad(f, argnums=(0, 1))(params, J)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    g_leaves = jax.tree_util.tree_leaves(g_params)
    assert len(leaves) == len(g_leaves) and len(leaves) > 0
    for i, leaf in enumerate(leaves):
        for idx in np.ndindex(leaf.shape):

            def at(d, i=i, idx=idx):
                new = list(leaves)
                new[i] = leaves[i].at[idx].add(d)
                return float(f(jax.tree_util.tree_unflatten(treedef, new), J))

            np.testing.assert_allclose(g_leaves[i][idx], (at(h) - at(-h)) / (2 * h), atol=1e-7)
    for idx in np.ndindex(3, 3):
        fd = (float(f(params, J.at[idx].add(h))) - float(f(params, J.at[idx].add(-h)))) / (2 * h)
        np.testing.assert_allclose(g_J[idx], fd, atol=1e-7)


def test_torque_parameter_gradients_match_finite_differences(rel_setup, rng):
    model, kin, ref = rel_setup
    J = jnp.asarray(ref["J"])
    c = jnp.asarray(rng.normal(size=3))
    torques = [
        rb.BodyTorque(rng.normal(size=3)),
        rb.InertialTorque(rng.normal(size=3)),
        rb.UniformGravity(1.3, rng.normal(size=3)),
        rb.RestoringMoment(0.8),
        rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([0.7, -0.4, 0.25]), 0.3), eps=0.3),
        rb.GravityGradient(1.7),
        rb.GravityGradient(0.5) + rb.UniformGravity(0.7, rng.normal(size=3)),
    ]
    for torque in torques:
        _fd_gradient_check(torque, kin, J, c)
    # BalancingTransport has no parameters; its derivative in J (J ε_e − J ω_e × ω_e):
    g = jax.grad(lambda J: jnp.dot(c, rb.BalancingTransport()(kin, J)))(J)
    w_e, e_e = np.asarray(kin.omega_e), np.asarray(kin.eps_e)
    # ∂/∂J_ij of cᵀ(J e − (J w) × w) = c_i e_j − (w × c)_i w_j
    np.testing.assert_allclose(g, np.outer(c, e_e) - np.outer(np.cross(w_e, c), w_e), atol=TIGHT)


@pytest.mark.parametrize("name", ["uniform_gravity", "restoring_moment", "gravity_gradient", "sum"])
def test_potential_rate_is_minus_power(name, rng):
    """−dV/dt = ω·M for a conservative torque along any motion, and for a sum of them.

    (a) V along an explicit rotation path q(s) = q0 ⊗ exp(ω s) built with scipy, central FD;
    (b) `jax.jvp` of V along the hand kinematics q' = ½ q ⊗ (0, ω), exact to rounding.
    """
    J = general_inertia(rng, [1.0, 1.5, 2.2])
    torque = {
        "uniform_gravity": rb.UniformGravity(1.4, rng.normal(size=3)),
        "restoring_moment": rb.RestoringMoment(0.9),
        "gravity_gradient": rb.GravityGradient(2.1),
        "sum": rb.UniformGravity(1.4, rng.normal(size=3))
        + rb.GravityGradient(2.1)
        + rb.RestoringMoment(0.9)
        + rb.NoTorque(),
    }[name]
    model = rb.RigidBody(J, torque)
    Jj = model.inertia
    t = jnp.asarray(0.0)
    for _ in range(5):
        w, q0 = rng.normal(size=3), random_quat(rng)

        def V(q, w=w):
            return model.torque.potential(model.kinematics(t, rb.State(jnp.asarray(w), q)), Jj)

        def q_path(s, w=w, q0=q0):
            return jnp.asarray(
                xyzw_to_wxyz((scipy_rot(q0) * Rotation.from_rotvec(w * s)).as_quat())
            )

        power = float(
            np.dot(
                w, model.torque(model.kinematics(t, rb.State(jnp.asarray(w), jnp.asarray(q0))), Jj)
            )
        )
        dV_fd = (float(V(q_path(FD_H))) - float(V(q_path(-FD_H)))) / (2 * FD_H)
        np.testing.assert_allclose(dV_fd, -power, atol=FD_TOL)
        # q' = ½ q ⊗ (0, ω) by hand (Hamilton product with a pure quaternion)
        qw, qv = q0[0], q0[1:]
        q_dot = 0.5 * np.concatenate([[-np.dot(qv, w)], qw * w + np.cross(qv, w)])
        _, dV = jax.jvp(V, (jnp.asarray(q0),), (jnp.asarray(q_dot),))
        np.testing.assert_allclose(dV, -power, atol=TIGHT)
    assert abs(power) > 1e-3  # a non-trivial check


def test_conservative_torques_are_abstract_conservative_torques(rng):
    """The torques with a potential are `AbstractConservativeTorque`s (abstract: `potential`
    must be implemented); the others are not, and a sum has a potential exactly when each
    of its terms has one, the refusal naming the term that has none."""
    conservative = [
        rb.NoTorque(),
        rb.UniformGravity(1.4, rng.normal(size=3)),
        rb.GravityGradient(2.1),
        rb.RestoringMoment(0.9),
    ]
    other = [
        rb.BodyTorque(rng.normal(size=3)),
        rb.InertialTorque(rng.normal(size=3)),
        rb.BalancingTransport(),
        conservative[1] + conservative[2],
    ]
    for torque in conservative:
        assert isinstance(torque, rb.AbstractConservativeTorque), type(torque).__name__
    for torque in other:
        assert not isinstance(torque, rb.AbstractConservativeTorque), type(torque).__name__
    assert rb.AbstractConservativeTorque is rb.torques.AbstractConservativeTorque
    assert issubclass(rb.AbstractConservativeTorque, rb.AbstractTorque)

    class NoPotential(rb.AbstractConservativeTorque):
        def __call__(self, kin, inertia):
            return jnp.zeros_like(kin.omega)

    with pytest.raises(TypeError, match="abstract"):
        NoPotential()

    model = rb.RigidBody(general_inertia(rng, [1.0, 1.5, 2.2]))
    kin = model.kinematics(
        jnp.asarray(0.3), rb.State(jnp.asarray(rng.normal(size=3)), jnp.asarray(random_quat(rng)))
    )
    J = model.inertia
    assert float(rb.NoTorque().potential(kin, J)) == 0.0
    total = sum(conservative[1:], conservative[0])
    np.testing.assert_allclose(
        total.potential(kin, J), sum(float(t.potential(kin, J)) for t in conservative), rtol=TIGHT
    )
    with pytest.raises(ValueError, match="BodyTorque has no potential energy.*GravityGradient"):
        (rb.GravityGradient(2.1) + other[0]).potential(kin, J)
    k = rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([0.7, -0.4]), 0.3))
    with pytest.raises(ValueError, match="callable k"):
        k.potential(kin, J)
    with pytest.raises(ValueError, match="callable k"):
        (rb.GravityGradient(2.1) + k).potential(kin, J)


@pytest.mark.parametrize("name", ["BodyTorque", "InertialTorque"])
def test_energy_refuses_a_torque_with_no_potential(name):
    """`invariants.energy` names the torque with no potential, alone or in a sum (at trace
    time: shapes only)."""
    torque = (
        rb.BodyTorque(jnp.ones(3))
        if name == "BodyTorque"
        else rb.NoTorque() + rb.InertialTorque(jnp.ones(3))
    )
    model = rb.RigidBody(jnp.diag(jnp.array([1.0, 1.5, 2.2])), torque)
    traj = rb.Trajectory(
        ts=jnp.zeros(2),
        ys=rb.State(jnp.zeros((2, 3)), jnp.tile(jnp.eye(4)[0], (2, 1))),
        stats={},
        result=rb.RESULTS.successful,
    )
    with pytest.raises(ValueError, match=f"{name} has no potential energy"):
        jax.eval_shape(rb.invariants.energy, model, traj)


def test_a_polynomial_needs_its_coefficients():
    """`PolynomialSinPsi` refuses a scalar `coeffs` by name: a polynomial's coefficients
    are a vector (the last axis), not a number."""
    with pytest.raises(ValueError, match="`coeffs` must have shape"):
        rb.PolynomialSinPsi(1.0, 0.1)
    assert rb.PolynomialSinPsi([1.0], 0.1).K(2.0) == 1.0


def test_a_scalar_parameter_takes_no_batch_axes():
    """A scalar parameter given as a vector is refused by name: a 3-vector `weight` would
    broadcast against the lever and scale the torque per component, a wrong torque with no
    error. A batch of models is built by `eqx.filter_vmap`, whose constructor sees one
    scalar: that batch solves as each model alone does (1e-12: the same steps)."""
    J = jnp.diag(jnp.array([2.0, 3.0, 4.0]))
    v = jnp.array([1.0, 2.0, 3.0])
    for make, name in (
        (lambda: rb.UniformGravity(v, jnp.array([0.0, 0.0, 1.0])), "weight"),
        (lambda: rb.GravityGradient(v), "eps"),
        (lambda: rb.RestoringMoment(v), "k"),
        (lambda: rb.RestoringMoment(1.0, eps=v), "eps"),
        (lambda: rb.PolynomialSinPsi(jnp.array([1.0]), v), "eps"),
        (lambda: rb.CircularOrbit(jnp.array([0.5])), "n"),
    ):
        with pytest.raises(ValueError, match=f"`{name}` must be a scalar, got shape"):
            make()
    ts = jnp.linspace(0.0, 2.0, 3)
    y0 = rb.State(jnp.array([0.3, -0.5, 1.2]), jnp.array([1.0, 0.0, 0.0, 0.0]))
    models = eqx.filter_vmap(lambda e: rb.RigidBody(J, rb.GravityGradient(e)))(v)
    batch = rb.simulate_batch(
        models,
        jax.tree_util.tree_map(lambda x: jnp.stack([x] * 3), y0),
        ts,
        model_axes=0,
        rtol=1e-10,
        atol=1e-10,
    )
    for i, e in enumerate(v):
        one = rb.simulate(rb.RigidBody(J, rb.GravityGradient(e)), y0, ts, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(batch.ys.omega[i], one.ys.omega, rtol=0, atol=1e-12)
