"""The compile layer's way in (`rbdyn_jax/_program/program.py`): a `Program` traces its
function with the runtime checks as NaN exactly where the inputs its checks read are
concrete, raises through them otherwise, and leaves equinox's check mode as it found it,
also when two threads compile at once."""

import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbdyn_jax import _compat
from rbdyn_jax._program.program import Program, concrete


def positive_sqrt(x, scale):
    """A function with a runtime check on `x`, whose checks `scale` stands for."""
    x = eqx.error_if(x, jnp.any(x < 0), "`x` must be non-negative.")
    return jnp.sqrt(x) * scale


def program():
    return Program(positive_sqrt, validated=lambda x, scale: scale)


def test_concrete_inputs_give_nan_and_traced_ones_raise():
    run = program()
    assert run.checks_nan(jnp.ones(2), 2.0) and run.checks_nan(jnp.ones(2), jnp.asarray(2.0))
    out = run(jnp.array([4.0, -1.0]), jnp.asarray(2.0))  # the check gives NaN: no raise
    assert np.isnan(np.asarray(out)).all() and out.shape == (2,)
    np.testing.assert_array_equal(run(jnp.array([4.0, 9.0]), jnp.asarray(2.0)), [4.0, 6.0])
    under_jit = jax.jit(lambda x, s: run(x, s))  # `scale` traced: the check raises
    np.testing.assert_array_equal(under_jit(jnp.array([4.0, 9.0]), 2.0), [4.0, 6.0])
    with pytest.raises(Exception, match="must be non-negative"):
        jax.block_until_ready(under_jit(jnp.array([4.0, -1.0]), 2.0))
    assert _compat.error_mode() == "raise"  # as before the calls


def test_validated_none_means_every_call_and_concrete_sees_tracers():
    run = Program(positive_sqrt)
    assert run.checks_nan(jnp.ones(2), 1.0)
    assert np.isnan(np.asarray(run(jnp.array([-1.0]), 1.0))).all()
    assert concrete(np.ones(2), {"a": 1.0}, None)
    seen = []
    jax.jit(lambda x: seen.append(concrete(x, 1.0)) or x)(1.0)
    assert seen == [False]


def test_two_threads_compiling_at_once_keep_their_modes():
    """The check mode is a process-wide setting of equinox's, set for one trace at a time
    under a lock every `Program` takes: a thread tracing a program whose checks raise while
    another traces one with its checks as NaN still gets its raising check."""
    nan_run, failures = program(), []
    checked = jax.jit(lambda x, s: nan_run(x, s))

    def nan_side():
        for k in range(8):  # a new shape each time: a new trace
            out = nan_run(-jnp.ones(k + 1), jnp.asarray(1.0))
            if not np.isnan(np.asarray(out)).all():
                failures.append("nan")

    def raising_side():
        for k in range(8):
            try:
                jax.block_until_ready(checked(-jnp.ones(k + 1), 1.0))
                failures.append("raise")
            except Exception as e:  # noqa: BLE001 - equinox's runtime error
                if "must be non-negative" not in str(e):
                    failures.append(str(e))

    threads = [threading.Thread(target=nan_side), threading.Thread(target=raising_side)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == []
    assert _compat.error_mode() == "raise"


def test_a_trace_inside_a_nan_program_is_not_reused_by_a_raising_one():
    """A program traced with its checks as NaN (a fit) calls another program on traced
    inputs (its solves): that inner trace takes the NaN mode. A later caller's own trace of
    the inner program, in the raising mode, must trace anew and raise, not reuse it."""
    inner = program()
    outer = Program(lambda x, s: inner(x, s * 1.0))  # `s * 1.0`: traced inside
    assert np.isnan(np.asarray(outer(jnp.array([-1.0, 4.0]), jnp.asarray(2.0)))).all()
    under_jit = jax.jit(lambda x, s: inner(x, s))
    with pytest.raises(Exception, match="must be non-negative"):
        jax.block_until_ready(under_jit(jnp.array([-1.0, 4.0]), 2.0))
    # and the other order: the raising trace is not taken into the NaN program either
    assert np.isnan(np.asarray(outer(jnp.array([-1.0, 9.0]), jnp.asarray(3.0)))).all()
