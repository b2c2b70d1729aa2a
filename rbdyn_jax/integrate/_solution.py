"""What a solve returns: `Trajectory` and its `RESULTS` codes."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from .. import _compat


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """Outcome of a solve: diffrax's codes (`successful`, `max_steps_reached`, …) and one
    of ours. The text of each item is its error message."""

    nonfinite_state = (
        "The state or its derivative is not finite (NaN or inf, or a zero quaternion): "
        "check the initial condition and the model's parameters."
    )


def result_code(result) -> Array:
    """The integer code (an int32 array) of a `RESULTS` item, e.g. to store it; the names
    of the codes are `result_names()`.

    diffrax's codes are the first of ours with the same values (tested), so promoting one
    is the identity on its value. `RESULTS.promote` would look the value up in a table
    eagerly while the solve is traced, compiling small programs on a first call."""
    return jnp.asarray(_compat.result_value(result), jnp.int32)


def as_result(values) -> RESULTS:
    """A `RESULTS` item holding an integer array of codes (as the lane loop carries them)."""
    return _compat.result_with_value(RESULTS.successful, values)


def result_names() -> dict[int, str]:
    """`{code: name}` of every `RESULTS` item."""
    return {
        int(_compat.result_value(item)): name
        for name, item in _compat.result_names(RESULTS).items()
    }


class Trajectory(eqx.Module):
    """A solved trajectory.

    **Fields:**

    - `ts`: `(n,)` output times.
    - `ys`: the state at `ts`, with a leading time axis on every leaf (a `State` for the
      quaternion models). Quaternions (and γ in the Poisson form) are renormalised.
    - `stats`: dict of diffrax's step counts (`num_steps`, `num_accepted_steps`,
      `num_rejected_steps`) and `norm_drift`, the largest deviation of |q| (|γ| in the
      Poisson form) from 1 that the renormalisation removed.
    - `result`: a `RESULTS` item; `RESULTS.successful` when the solve succeeded.

    From `simulate_batch` every leaf has a further leading batch axis.
    """

    ts: Float[Array, "*batch n"]
    ys: PyTree
    stats: dict
    result: RESULTS


def succeeded_now(result: RESULTS) -> bool:
    """Whether every code of a concrete `result` is `successful`, read on the host (`False`
    for a traced one): `throw`'s check then needs no `error_if`, whose eager comparison
    compiles two programs on first use."""
    code = _compat.result_value(result)
    return not isinstance(code, jax.core.Tracer) and bool(
        np.all(np.asarray(code) == np.asarray(_compat.result_value(RESULTS.successful)))
    )


def thrown(traj: Trajectory) -> Trajectory:
    """`traj`, raising at run time (`eqx.error_if`) if any of its results failed."""
    if succeeded_now(traj.result):
        return traj
    if not isinstance(_compat.result_value(traj.result), jax.core.Tracer):
        # A concrete batch may lie across several devices (the lane solver's); XLA aborts
        # the process when a host callback raises in a program over several devices, so
        # the check runs on one.
        traj = jax.device_put(traj, jax.local_devices()[0])
    # The codes take no derivative: under `jax.grad` outside `jit` they are traced for
    # differentiation, and the check's reduction has no derivative rule.
    result = jax.tree_util.tree_map(jax.lax.stop_gradient, traj.result)
    return result.error_if(traj, jnp.any(result != RESULTS.successful))
