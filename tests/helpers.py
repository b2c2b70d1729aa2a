"""Comparators and reference constructions shared by the tests."""

import importlib.util
import pathlib

import jax.extend.core
import numpy as np

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
