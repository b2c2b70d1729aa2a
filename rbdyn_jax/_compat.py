"""Every use rbdyn_jax makes of its dependencies' internals, in one place.

Each function here reaches past a public API because none exists for what it needs; the
rest of the package calls these, never the internals themselves. `tests/test_compat.py`
pins each behaviour relied on, so that a new diffrax, equinox or JAX that changes one
fails there, by name, rather than somewhere in a physics test.
"""

import contextlib

import equinox as eqx
import jax.numpy as jnp


def trace_state_clean() -> bool:
    """Whether nothing is being traced now (JAX has no public spelling)."""
    from jax._src import core

    return core.trace_state_clean()


def backends_are_initialized() -> bool:
    """Whether JAX's backends have started, after which XLA_FLAGS are no longer read
    (JAX has no public spelling)."""
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def uncommitted(x):
    """The JAX array `x` as one not committed to its devices, as `jit` returns when none
    of its inputs is committed (JAX has no public spelling): a stored program's call
    (`jax.export`) commits its outputs, where the same program traced by `jit` would
    leave them free to move to another device's computation."""
    from jax._src import array

    return array.ArrayImpl(x.aval, x.sharding, x._arrays, committed=False)


def wrapped_term(term):
    """`term` as `diffrax.diffeqsolve` hands it to its solver (`WrapTerm(term, 1)`), for a
    loop that drives the solver's step itself and must take bitwise the same steps."""
    from diffrax._term import WrapTerm

    return WrapTerm(term, 1)


def unwrapped_term(terms):
    """The term a solver was given by `diffrax.diffeqsolve` as the caller's term and the
    direction of time (+1, or −1 for a solve from a later time to an earlier one):
    diffeqsolve hands its solver `WrapTerm(term, direction)`, which runs the caller's term
    at `direction · t`. A term not so wrapped (a solver stepped by hand) is its own,
    direction +1. For a solver that needs the model behind the term, not only its vector
    field (`integrate.LiePoissonSplitting`)."""
    from diffrax._term import WrapTerm

    if isinstance(terms, WrapTerm):
        return terms.term, terms.direction
    return terms, 1


def result_value(item):
    """The integer code of a result item of a `diffrax.RESULTS`-like enumeration (an int32
    array, traced or not), read without the table lookup of `RESULTS.promote`."""
    return item._value


def result_with_value(item, values):
    """A result item of `item`'s enumeration holding the integer codes `values`."""
    return eqx.tree_at(lambda r: r._value, item, jnp.asarray(values, jnp.int32))


def result_names(results) -> dict:
    """`{name: item}` of every item of a `diffrax.RESULTS`-like enumeration class."""
    return dict(results._name_to_item)


def _errors_module():
    import equinox._errors as errors

    return errors


def error_mode() -> str | None:
    """Equinox's current `eqx.error_if` mode (`EQX_ON_ERROR`: "raise", "nan", …), read
    by equinox when a check is traced; `None` if this equinox has no such switch."""
    return getattr(_errors_module(), "EQX_ON_ERROR", None)


def forget_error_traces(jitted=()) -> None:
    """Drop the cached traces of equinox's jitted `error_if` helper, of
    `diffrax.diffeqsolve` (an `eqx.filter_jit` function) and of the `eqx.filter_jit`
    functions `jitted`: JAX keys a cached trace by its inputs, not by the error mode, so a
    trace made in one mode must not be reused in the other."""
    import diffrax

    helper = getattr(_errors_module(), "branched_error_if_impl_jit", None)
    for f in (helper, diffrax.diffeqsolve, *jitted):
        clear = getattr(getattr(f, "_cached", None), "clear_cache", None)
        if clear is not None:
            clear()


@contextlib.contextmanager
def error_mode_set(mode: str, jitted=()):
    """Equinox's `eqx.error_if` mode set to `mode` while the block runs (the traces of
    `jitted` dropped on the way in and out, `forget_error_traces`). A no-op where equinox
    has no such switch."""
    errors = _errors_module()
    old = getattr(errors, "EQX_ON_ERROR", None)
    if old is None:
        yield
        return
    forget_error_traces(jitted)
    errors.EQX_ON_ERROR = mode
    try:
        yield
    finally:
        errors.EQX_ON_ERROR = old
        forget_error_traces(jitted)
