"""XLA's process-wide flags (`XLA_FLAGS`) for rbdyn_jax's solves, set without importing JAX.

XLA reads `XLA_FLAGS` once, when JAX starts its backend (at the first computation, not at
`import jax`), so the flags must be in the environment before then. `import rbdyn_jax`
sets them (`configure_on_import`): one XLA CPU device per core this process may run on,
since the lane solver splits a batch over all local devices and one XLA CPU device keeps
about one core busy on these solves, and every while loop compiled whole. It leaves
alone:

- what `XLA_FLAGS` already says: a device count or a loop threshold there is kept, and
  other backend options are kept beside the loop threshold;
- a process whose JAX backend is running: XLA has read its flags (nothing changes and
  nothing is raised);
- every flag, when `RBDYN_JAX_CONFIGURE_XLA=0` is in the environment.

An explicit `configure_xla(host_devices=k)` before JAX starts replaces the device count that
the import set (and only that one), so `k` devices start.

This module imports no JAX: `import rbdyn_jax` stays cheap, and a process that never
computes (`rbdyn --help`) never loads JAX.
"""

import numbers
import os
import sys

# XLA:CPU runs a program as a graph of "thunks" (a fused kernel, a loop, a call…) that its
# runtime dispatches one by one, again at every iteration of a while loop. A while loop
# whose accessed bytes are under a threshold is hoisted instead into one call compiled as a
# single function (XLA's `SmallWhileLoopHoistingPass`; not for loops holding a scatter,
# sort or custom call, and a scatter is a loop of its own under the classic emitters of
# `COMPILER_OPTIONS`). The default threshold is small; this one hoists every such loop.
# The option lives in `xla_backend_extra_options`, a map that compiler options cannot set.
LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
LOOP_BYTES = 1 << 40
DEVICE_COUNT = "--xla_force_host_platform_device_count"
EXTRA_OPTIONS = "--xla_backend_extra_options="
# `RBDYN_JAX_CONFIGURE_XLA=0`: `import rbdyn_jax` leaves XLA's flags alone.
OPT_OUT = "RBDYN_JAX_CONFIGURE_XLA"

# The device-count flag `configure_on_import` added to this process's `XLA_FLAGS` (None if
# it added none, or once an explicit `configure_xla(host_devices=…)` has replaced it). A
# count inherited from a parent process is the environment's, and is kept like a user's.
_count_set_on_import: str | None = None


def backend_started() -> bool:
    """Whether JAX's backend is running (and has read XLA_FLAGS). Without JAX imported it
    cannot be, and JAX is not imported to find out."""
    if "jax" not in sys.modules:
        return False
    from .. import _compat

    return _compat.backends_are_initialized()


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the system keeps one (a
    process limited to k cores gets k), else every core of the machine."""
    if hasattr(os, "process_cpu_count"):  # Python ≥ 3.13: affinity, or PYTHON_CPU_COUNT
        n = os.process_cpu_count()
    elif hasattr(os, "sched_getaffinity"):
        n = len(os.sched_getaffinity(0))
    else:
        n = os.cpu_count()
    return max(1, n or 1)


def merged_flags(old: str, host_devices: int | None, replaceable: str | None = None) -> str:
    """`old` (an `XLA_FLAGS` value) with the loop threshold and, if `host_devices` is given,
    the device count added, each only where `old` does not set it already; a device count
    equal to `replaceable` (the only one in `old`) is replaced by `host_devices`."""
    flags = old.split()
    backend = [i for i, f in enumerate(flags) if f.startswith(EXTRA_OPTIONS)]
    if not backend:
        flags.append(f"{EXTRA_OPTIONS}{LOOP_OPTION}={LOOP_BYTES}")
    else:  # XLA keeps the last; add to it unless the threshold is already there
        i = backend[-1]
        options = [o for o in flags[i][len(EXTRA_OPTIONS) :].split(",") if o]
        if not any(o.split("=")[0] == LOOP_OPTION for o in options):
            flags[i] = EXTRA_OPTIONS + ",".join([*options, f"{LOOP_OPTION}={LOOP_BYTES}"])
    if host_devices is not None:
        counts = [i for i, f in enumerate(flags) if f.startswith(DEVICE_COUNT)]
        if not counts:
            flags.append(f"{DEVICE_COUNT}={int(host_devices)}")
        elif replaceable is not None and [flags[i] for i in counts] == [replaceable]:
            flags[counts[0]] = f"{DEVICE_COUNT}={int(host_devices)}"
    return " ".join(flags)


def configure_xla(host_devices: int | None = None) -> str:
    """Set `XLA_FLAGS` for rbdyn_jax's solves on CPU, before JAX computes anything.

    `import rbdyn_jax` calls it with one device per core the process may run on (its CPU
    affinity), unless JAX has already computed something (XLA has then read its flags) or
    `RBDYN_JAX_CONFIGURE_XLA=0` is in the environment. Call it yourself for another device
    count, or for these flags after opting out.

    - Every while loop XLA:CPU can compile as one function is compiled so (`LOOP_OPTION`),
      without its runtime's dispatch of each kernel at every iteration: the lane solver
      (most of all with few lanes), the vmapped `diffeqsolve` and gradients through the
      lanes run faster than with XLA's defaults, for a slightly longer first compilation
      (the performance page, docs/performance.md). The trajectories, steps and gradients
      are the same (tested).
    - `host_devices`: if given, XLA starts that many CPU devices
      (`--xla_force_host_platform_device_count`), so that the lane solver and the sweep
      can use every core (`simulate_batch(..., devices=…)`). It replaces the count that
      `import rbdyn_jax` set.

    Flags already in `XLA_FLAGS` otherwise win: a device count or a loop threshold set
    there (by you, by an earlier call, or inherited from a parent process) is kept, and
    other backend options are kept beside this one. Other backends ignore both flags.

    **Returns:** the new `XLA_FLAGS`.

    **Raises:** `RuntimeError` if JAX's backend is already running and the flags would
    change: XLA read them when it started, so they would have no effect.
    """
    global _count_set_on_import
    if host_devices is not None and (
        isinstance(host_devices, bool)
        or not isinstance(host_devices, numbers.Integral)
        or host_devices < 1
    ):
        raise ValueError(f"`host_devices` must be a positive int or None, got {host_devices!r}.")
    old = os.environ.get("XLA_FLAGS", "")
    new = merged_flags(old, host_devices, _count_set_on_import)
    if new != old:
        if backend_started():
            raise RuntimeError(
                "JAX's backend is already running, and XLA reads XLA_FLAGS only when it "
                "starts: call `configure_xla` before the first JAX computation, or start "
                f"Python with XLA_FLAGS='{new}'."
            )
        os.environ["XLA_FLAGS"] = new
    if host_devices is not None:
        _count_set_on_import = None  # from here on the count is the caller's
    return new


def configure_on_import() -> None:
    """`configure_xla(host_devices=usable_cores())` when `import rbdyn_jax` runs, unless
    `RBDYN_JAX_CONFIGURE_XLA=0` or JAX's backend is running (then nothing, silently);
    remembers the device count it added, which an explicit `configure_xla` may replace."""
    global _count_set_on_import
    if os.environ.get(OPT_OUT, "1") == "0" or backend_started():
        return
    n = usable_cores()
    theirs = any(f.startswith(DEVICE_COUNT) for f in os.environ.get("XLA_FLAGS", "").split())
    configure_xla(host_devices=n)
    if not theirs:
        _count_set_on_import = f"{DEVICE_COUNT}={n}"


def loops_compiled_whole() -> bool:
    """Whether XLA:CPU was told to compile every while loop whole (`configure_xla`, or the
    same option in the user's `XLA_FLAGS`)."""
    return f"{LOOP_OPTION}=" in os.environ.get("XLA_FLAGS", "")
