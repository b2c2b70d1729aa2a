"""How rbdyn_jax compiles: every program it compiles goes through `jit` or `filter_jit`
here, which pass `COMPILER_OPTIONS` to XLA.

XLA:CPU compiles each fused kernel of a program through its MLIR "fusion emitters" by
default. Its classic emitters compile a solver program (~100 kernels) markedly faster,
and the program runs as fast (the performance page, docs/performance.md).
`xla_cpu_use_fusion_emitters` is a field of XLA's `DebugOptions`; only the CPU backend
reads it.

JAX takes compiler options only from the outermost `jit` of a program (a nested one
raises). So the wrappers here pass them when called at the top level and are plain jits
inside a caller's transformation, whose program compiles with the caller's options: pass
`compiler_options=rbdyn_jax.COMPILER_OPTIONS` to your own `jax.jit` for the same saving.

`configure_xla` sets what compiler options cannot: XLA's process-wide flags (`XLA_FLAGS`),
read once when JAX starts its backend.
"""

import functools
import numbers
import os

import equinox as eqx
import jax

from . import _compat

COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

# XLA:CPU runs a program as a graph of "thunks" (a fused kernel, a loop, a call…) that its
# runtime dispatches one by one, again at every iteration of a while loop. A while loop
# whose accessed bytes are under a threshold is hoisted instead into one call compiled as a
# single function (XLA's `SmallWhileLoopHoistingPass`; not for loops holding a scatter,
# sort or custom call, and a scatter is a loop of its own under the classic emitters of
# `COMPILER_OPTIONS`). The default threshold is small; this one hoists every such loop.
# The option lives in `xla_backend_extra_options`, a map that compiler options cannot set.
LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
LOOP_BYTES = 1 << 40


def backend_started() -> bool:
    """Whether JAX's backend is running (and has read XLA_FLAGS)."""
    return _compat.backends_are_initialized()


def configure_xla(host_devices: int | None = None) -> str:
    """Set `XLA_FLAGS` for rbdyn_jax's solves on CPU; call it before JAX computes anything.

    - Every while loop XLA:CPU can compile as one function is compiled so (`LOOP_OPTION`),
      without its runtime's dispatch of each kernel at every iteration: the lane solver
      (most of all with few lanes), the vmapped `diffeqsolve` and gradients through the
      lanes run faster than with XLA's defaults, for a slightly longer first compilation
      (the performance page, docs/performance.md). The trajectories, steps and gradients
      are the same (tested).
    - `host_devices`: if given, XLA starts that many CPU devices
      (`--xla_force_host_platform_device_count`), so that the lane solver and the sweep
      can use every core (`simulate_batch(..., devices=…)`).

    Flags already in `XLA_FLAGS` win: a device count or a loop threshold set there is kept,
    and other backend options are kept beside this one. Other backends ignore both flags.

    **Returns:** the new `XLA_FLAGS`.

    **Raises:** `RuntimeError` if JAX's backend is already running and the flags would
    change: XLA read them when it started, so they would have no effect.
    """
    if host_devices is not None and (
            isinstance(host_devices, bool) or not isinstance(host_devices, numbers.Integral)
            or host_devices < 1):
        raise ValueError(f"`host_devices` must be a positive int or None, got {host_devices!r}.")
    old = os.environ.get("XLA_FLAGS", "")
    flags = old.split()
    extra = "--xla_backend_extra_options="
    backend = [i for i, f in enumerate(flags) if f.startswith(extra)]
    if not backend:
        flags.append(f"{extra}{LOOP_OPTION}={LOOP_BYTES}")
    else:  # XLA keeps the last; add to it unless the threshold is already there
        i = backend[-1]
        options = [o for o in flags[i][len(extra):].split(",") if o]
        if not any(o.split("=")[0] == LOOP_OPTION for o in options):
            flags[i] = extra + ",".join([*options, f"{LOOP_OPTION}={LOOP_BYTES}"])
    count = "--xla_force_host_platform_device_count"
    if host_devices is not None and not any(f.startswith(count) for f in flags):
        flags.append(f"{count}={int(host_devices)}")
    new = " ".join(flags)
    if new != old:
        if backend_started():
            raise RuntimeError(
                "JAX's backend is already running, and XLA reads XLA_FLAGS only when it "
                "starts: call `configure_xla` before the first JAX computation, or start "
                f"Python with XLA_FLAGS='{new}'.")
        os.environ["XLA_FLAGS"] = new
    return new


def top_level() -> bool:
    """Whether nothing is being traced now: a jitted call here compiles its own program."""
    return _compat.trace_state_clean()


def _dispatch(jitter, fn):
    own, nested = jitter(fn, compiler_options=COMPILER_OPTIONS), jitter(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        return (own if top_level() else nested)(*args, **kwargs)

    return call


def jit(fn):
    """`jax.jit(fn)`, compiled with `COMPILER_OPTIONS` when called at the top level."""
    return _dispatch(jax.jit, fn)


def filter_jit(fn):
    """`eqx.filter_jit(fn)`, compiled with `COMPILER_OPTIONS` when called at the top level."""
    return _dispatch(eqx.filter_jit, fn)


def nested_filter_jit(fn):
    """`eqx.filter_jit(fn)` for a function called only while a program is traced (it never
    compiles a program of its own, so it needs no options). JAX traces it once per input
    structure and the enclosing program holds one `jit` call per use; the trace, its
    batching under `vmap` and its lowering are then shared by every use of that structure.
    Its cached traces are cleared like `diffrax.diffeqsolve`'s when the check mode
    changes (`_checks.checks_as_nan`)."""
    return eqx.filter_jit(fn)


def export(fn):
    """`jax.export.export(jax.jit(fn))`: `fn` traced and lowered, for storing (`_traces.py`).
    Nothing is compiled here; the exported program is compiled through `jit`."""
    return jax.export.export(jax.jit(fn))


def loops_compiled_whole() -> bool:
    """Whether XLA:CPU was told to compile every while loop whole (`configure_xla`, or the
    same option in the user's `XLA_FLAGS`)."""
    return f"{LOOP_OPTION}=" in os.environ.get("XLA_FLAGS", "")
