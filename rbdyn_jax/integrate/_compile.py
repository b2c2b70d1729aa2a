"""When a solve is compiled, and which of its programs may be stored.

Every public solve goes through `compiled`: one `eqx.filter_jit` per solve *structure*, so
new parameter values, initial conditions, times or tolerances reuse the compiled program.
Inputs validated before tracing (concrete, not traced) take a second wrapper whose trace
has its runtime checks as NaN: that program holds no host callback, so JAX's persistent
compilation cache can store it, and rbdyn_jax's cache of traced programs
(`rbdyn_jax/_traces.py`) stores its trace beside it.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import _compat, _traces
from .._checks import checks_as_nan
from .._xla import filter_jit
from ._field import MODE_DEPENDENT_JITS
from ._solution import RESULTS


def compiled(fn):
    """`fn` under `eqx.filter_jit` twice: `[False]` keeps the runtime checks (host
    callbacks); `[True]` is traced with the checks as NaN (`checks_as_nan`), for inputs
    validated before tracing: its program can be stored in JAX's persistent compilation
    cache, and its trace in rbdyn_jax's beside it. Two wrappers, so that the two kinds of
    trace never share a cache entry."""

    @functools.wraps(fn)
    def checks_nan(*args):
        with checks_as_nan(jitted=MODE_DEPENDENT_JITS):
            return fn(*args)

    return {False: filter_jit(fn), True: _traces.cached(checks_nan)}


def cacheable(*xs) -> bool:
    """Whether the inputs were validated before tracing (concrete, not traced): the solve
    is then traced with its checks as NaN, holds no host callback, and JAX's persistent
    compilation cache can store it."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def succeeded_now(result: RESULTS) -> bool:
    """Whether every code of a concrete `result` is `successful`, read on the host (`False`
    for a traced one): `throw`'s check then needs no `error_if`, whose eager comparison
    compiles two programs on first use."""
    code = _compat.result_value(result)
    return not isinstance(code, jax.core.Tracer) and bool(
        np.all(np.asarray(code) == np.asarray(_compat.result_value(RESULTS.successful))))


def thrown(traj):
    """`traj`, raising at run time (`eqx.error_if`) if any of its results failed."""
    if succeeded_now(traj.result):
        return traj
    if not isinstance(_compat.result_value(traj.result), jax.core.Tracer):
        # A concrete batch may lie across several devices (the lane solver's); XLA aborts
        # the process when a host callback raises in a program over several devices, so
        # the check runs on one.
        traj = jax.device_put(traj, jax.local_devices()[0])
    return traj.result.error_if(traj, jnp.any(traj.result != RESULTS.successful))
