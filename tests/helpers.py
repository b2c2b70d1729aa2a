"""Comparators and reference constructions shared by the tests."""

import importlib.util
import pathlib

import equinox as eqx
import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"


def load_example(name: str):
    """Import `examples/<name>.py` by path (the examples are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_quat_equal(q1, q2, atol):
    """Quaternions equal up to the sign ambiguity q ≡ −q (both represent one rotation)."""
    q1 = np.asarray(q1)
    q2 = np.asarray(q2)
    s = np.sign(np.sum(q1 * q2, axis=-1, keepdims=True))
    s = np.where(s == 0, 1.0, s)
    np.testing.assert_allclose(q1, s * q2, atol=atol, rtol=0)


def wxyz_to_xyzw(q):
    q = np.asarray(q)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def xyzw_to_wxyz(q):
    q = np.asarray(q)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def skew(w):
    """[w]× such that skew(w) @ v = w × v (NumPy, independent of the package)."""
    w = np.asarray(w)
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def random_rotation_matrices(rng, n):
    """Uniform random rotations from scipy (an independent implementation)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()


def equations(jaxpr):
    """Every equation of a (closed) jaxpr and of its sub-jaxprs (loop bodies, `jit` calls,
    …)."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)  # a ClosedJaxpr's own jaxpr
    for eqn in jaxpr.eqns:
        yield eqn
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            yield from equations(sub)


def host_callbacks(jaxpr) -> list[str]:
    """The host-callback primitives (`pure_callback`, `io_callback`, `debug_callback`) of a
    (closed) jaxpr and its sub-jaxprs: a program holding one is never stored in JAX's
    persistent compilation cache."""
    return [e.primitive.name for e in equations(jaxpr) if "callback" in e.primitive.name]


def cheapest_call(jaxpr, eliminate=True):
    """The one `rbdyn_cheapest` equation of a (closed) jaxpr, after JAX's dead-code
    elimination (`dce_jaxpr`, which `jit` runs before lowering) unless `eliminate` is
    false: its `params["chosen"]` is the program the compiled program runs."""
    from jax.interpreters import partial_eval as pe

    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    if eliminate:
        jaxpr, _ = pe.dce_jaxpr(jaxpr, [True] * len(jaxpr.outvars))
    (call,) = [e for e in equations(jaxpr) if e.primitive.name == "rbdyn_cheapest"]
    return call


# ------------------------------------------------------------------------------------------
# Models, torques and frames (test_models.py, test_torques.py, test_frames.py): independent
# references in NumPy / scipy
# ------------------------------------------------------------------------------------------

# Unit-level identities: a handful of float64 operations on O(1) numbers.
TIGHT = 1e-12
# Central differences with h = 1e-5: truncation ~1e-10·|f'''|, rounding ~1e-11.
FD_H = 1e-5
FD_TOL = 1e-8
E_Z = np.array([0.0, 0.0, 1.0])


def scipy_rot(q):
    """scipy Rotation of a scalar-first quaternion (or a batch of them)."""
    return Rotation.from_quat(wxyz_to_xyzw(np.asarray(q)))


def general_inertia(rng, moments):
    """J = C diag(moments) Cᵀ with a scipy random rotation C (products of inertia ≠ 0)."""
    C = Rotation.random(random_state=rng).as_matrix()
    return C @ np.diag(moments) @ C.T


def random_quat(rng):
    return xyzw_to_wxyz(Rotation.random(random_state=rng).as_quat())


def vee(W):
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def zxz(q):
    """(ψ, θ, φ) of a quaternion from scipy (docs/physics.md#euler-angles: intrinsic "ZXZ")."""
    return scipy_rot(q).as_euler("ZXZ")


class PolyAngles(eqx.Module):
    """Frame angles `angle_i(t) = c[i,0] + c[i,1] t + c[i,2] t² + c[i,3] sin t`.

    The coefficients are a leaf, so frames with different coefficients share one compile.
    """

    c: jax.Array

    def __call__(self, t):
        return self.c @ jnp.stack([jnp.ones_like(t), t, t * t, jnp.sin(t)])


def np_angles(c, t):
    c = np.asarray(c)
    return c[:, 0] + c[:, 1] * t + c[:, 2] * t * t + c[:, 3] * np.sin(t)


# A frame with time-varying ω_e and ε_e:
# (ψ_e, θ_e, φ_e) = (0.3 t, 0.6 + 0.2 sin t, −0.5 t + 0.1 t²).
FRAME_C = np.array([[0.0, 0.3, 0.0, 0.0], [0.6, 0.0, 0.0, 0.2], [0.0, -0.5, 0.1, 0.0]])


def frame_rot(c, seq, t):
    """The frame attitude O1 → O0 by scipy."""
    return Rotation.from_euler(seq, np_angles(c, t))


def frame_omega1(c, seq, t, h=FD_H):
    """ω_e¹ from central differences of scipy attitudes: R_eᵀ R_e' = [ω_e¹]×
    (docs/physics.md#direction-cosines)."""
    R = frame_rot(c, seq, t).as_matrix()
    dR = (frame_rot(c, seq, t + h).as_matrix() - frame_rot(c, seq, t - h).as_matrix()) / (2 * h)
    return vee(R.T @ dR)


def zxz_omega(angles, rates):
    """docs/physics.md#euler-angle-rates, literally: p = ψ' sinθ sinφ + θ' cosφ, …"""
    psi, th, ph = angles
    dpsi, dth, dph = rates
    return np.array(
        [
            dpsi * np.sin(th) * np.sin(ph) + dth * np.cos(ph),
            dpsi * np.sin(th) * np.cos(ph) - dth * np.sin(ph),
            dpsi * np.cos(th) + dph,
        ]
    )


def np_rates(c, t):
    c = np.asarray(c)
    return c[:, 1] + 2 * c[:, 2] * t + c[:, 3] * np.cos(t)


# Jitted evaluation (one compile per structure, shared across tests) is much faster than
# eager op-by-op dispatch of the nested `jvp`s in frames (test_frames.py's `eval_frame` too).
# (Python floats would be static under `filter_jit`: times are converted to arrays first.)
_eval_kinematics = eqx.filter_jit(lambda model, t, y: model.kinematics(t, y))


def eval_kinematics(model, t, y):
    return _eval_kinematics(model, jnp.asarray(t, dtype=jnp.float64), y)


def relative_setup(rng):
    """A relative model under a time-varying ZXZ frame, a random state and time, with every
    quantity a torque sees recomputed independently."""
    J = general_inertia(rng, [1.2, 1.9, 2.6])
    model = rb.RelativeRigidBody(J, rb.EulerAngleFrame(PolyAngles(jnp.asarray(FRAME_C))))
    t = 1.3
    w_r = rng.normal(size=3)
    q_r = random_quat(rng)
    kin = eval_kinematics(model, t, rb.State(jnp.asarray(w_r), jnp.asarray(q_r)))
    Rr = scipy_rot(q_r)
    Re = frame_rot(FRAME_C, "ZXZ", t)
    Ra = Re * Rr
    # ω_e¹ by the literal ZXZ formula with hand derivatives of the angles; ε_e¹ by FD of it.
    w_e1 = zxz_omega(np_angles(FRAME_C, t), np_rates(FRAME_C, t))
    e_e1 = (
        zxz_omega(np_angles(FRAME_C, t + FD_H), np_rates(FRAME_C, t + FD_H))
        - zxz_omega(np_angles(FRAME_C, t - FD_H), np_rates(FRAME_C, t - FD_H))
    ) / (2 * FD_H)
    ref = dict(
        J=J,
        t=t,
        w_r=w_r,
        q_r=q_r,
        Rr=Rr,
        Ra=Ra,
        w_e=Rr.inv().apply(w_e1),
        e_e=Rr.inv().apply(e_e1),
        gamma=Rr.inv().apply(E_Z),
        gamma0=Ra.inv().apply(E_Z),
        q_abs=xyzw_to_wxyz(Ra.as_quat()),
    )
    return model, kin, ref


def small_scenario(**over) -> dict:
    """A small torque-free sweep scenario (test_sweep.py, test_scenario.py): dispersed
    inertia, rates and attitude."""
    d = {
        "name": "small",
        "model": {
            "kind": "rigid_body",
            "inertia": {"principal": [1.0, 2.0, 2.5], "log_cholesky_sigma": 0.05},
        },
        "initial": {
            "omega": {"dist": "normal", "mean": [0.1, 1.0, 0.1], "std": 0.3},
            "attitude": {"dist": "uniform_so3"},
        },
        "time": {"t1": 4.0, "n": 9},
        "solver": {"rtol": 1e-9, "atol": 1e-9},
        "outputs": {"summaries": ["energy_drift", "max_abs_omega", "first_flip_time"]},
    }
    for k, v in over.items():
        d[k] = v
    return d


SWEEP_NAMES = (
    "omega",
    "quat",
    "inertia",
    "status",
    "num_steps",
    "energy_drift",
    "max_abs_omega",
    "first_flip_time",
)


def load_store(path, names=SWEEP_NAMES) -> dict:
    """The named arrays of a sweep store (those it has), read with zarr."""
    import zarr

    g = zarr.open_group(str(path), mode="r")
    return {k: g[k][:] for k in names if k in g}


def assert_same_arrays(a: dict, b: dict):
    """Bitwise equality of two `load_store` results (NaNs equal)."""
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True), k
