"""Runtime checks as NaN while a program is traced.

`eqx.error_if` checks (a model's inertia checks, diffrax's checks of `ts` and `dt0`, …)
raise through a host callback. A program holding a host callback is never stored by JAX's
persistent compilation cache, and XLA aborts a program over several devices whose callback
raises. Where a program's inputs were validated before tracing, its checks cannot fire on
good input, so `Program` traces it with its checks giving NaN instead: a NaN state is then
reported per trajectory (`RESULTS.nonfinite_state`), and the program can be stored.

Equinox reads its check mode from a process-wide setting (its error mode) when a check is
traced, and diffrax's own checks take no other: `as_nan` sets it for the duration of one
trace only, under a lock that every `Program` call takes (`exclusive`) before JAX looks up
its trace, so two threads never trace rbdyn_jax's programs in different modes at once (a
trace of your own in another thread, outside rbdyn_jax's programs, is not covered), and drops
the cached traces that depend on it on the way in and out (`_compat.error_mode_set`): the
`eqx.filter_jit` functions JAX traces once per input structure (`diffrax.diffeqsolve`,
and those registered by `mode_dependent`), whose cache is keyed by their inputs, not the mode.
"""

import contextlib
import threading

from .. import _compat

_LOCK = threading.RLock()
_MODE_DEPENDENT: list = []  # jitted functions whose traces to drop on a switch


def mode_dependent(*jitted):
    """Register the `eqx.filter_jit` functions `jitted`, traced inside programs: their
    cached traces are dropped when `as_nan` switches the check mode. Returns the first."""
    _MODE_DEPENDENT.extend(jitted)
    return jitted[0]


@contextlib.contextmanager
def exclusive():
    """The block runs while no other thread runs a `Program` (which may trace in either
    mode): every `Program` call takes this lock, before JAX looks up its trace."""
    with _LOCK:
        yield


@contextlib.contextmanager
def as_nan():
    """While the block traces a program, `eqx.error_if` checks give NaN instead of raising
    (a no-op where equinox has no such mode: the program is then still correct, only not
    storable)."""
    with _LOCK, _compat.error_mode_set("nan", tuple(_MODE_DEPENDENT)):
        yield
