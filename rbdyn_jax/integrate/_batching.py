"""How `simulate_batch` runs a batch: the batching strategies `Vmap`, `Lanes` and `Kernel`,
and the default that picks the faster one."""

import abc
import dataclasses
import functools
import math
import numbers

import diffrax
import equinox as eqx
import jax

from .._program import traces
from .._program.devices import mesh as device_mesh, on_mesh, platform
from .._program.flags import loops_compiled_whole
from .._program.program import Program
from .._program.xla import top_level
from ._dealt import dealt
from ._diffeqsolve import solve_vmapped
from ._field import checked_before_tracing
from ._kernel_layout import kernel_block
from ._kernel_refusal import field_refuse
from ._kernel_solve import kernel_compiled, kernel_interpreted
from ._lane_loop import LAYOUTS, lane_loop
from ._lane_step import step_refuse
from ._sensitivity import sensitivity_solve
from ._solution import Trajectory


class AbstractBatching(eqx.Module):
    """How `simulate_batch` runs a batch of trajectories. Pass an instance as its
    `batching=` argument; `None` chooses for you (on a GPU `Kernel` where it serves; else
    `Lanes` where it serves; else `Vmap`)."""

    @abc.abstractmethod
    def solve(
        self, model, y0s, ts, *, solver, controller, adjoint, max_steps, dt0, model_axes
    ) -> Trajectory:
        """The batch's `Trajectory` (leading batch axis on every leaf)."""


class Vmap(AbstractBatching):
    """`diffrax.diffeqsolve` vmapped over the batch: every trajectory steps until the
    slowest has finished. Takes any solver, step-size controller and `adjoint` that
    diffeqsolve takes (default `RecursiveCheckpointAdjoint()`), and differentiates through
    that adjoint. Choose it for an implicit solver, a chosen adjoint, or reverse-over-reverse
    derivatives; the default takes it where `Lanes` cannot run the solve."""

    def solve(
        self, model, y0s, ts, *, solver, controller, adjoint, max_steps, dt0, model_axes
    ) -> Trajectory:
        adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
        return _vmapped(model, y0s, ts, solver, controller, adjoint, max_steps, dt0, model_axes)


class Lanes(AbstractBatching):
    """The lane solver, the fast path for batches: each device runs `lanes` lanes of one
    loop that drives diffrax's solver step and step-size controller itself, and a lane
    whose trajectory has finished takes the next one at once, so no lane idles behind the
    slowest trajectory. The default wherever it can run the solve, but for a solve `Kernel`
    runs on a GPU.

    **Arguments:**

    - `lanes`: lanes per device; `None` chooses from the batch size, the device count and
      the backend (`default_lanes`): on a CPU a few dozen, each device's share refilled
      through them; on an accelerator a lane per trajectory for up to 16,384 of them, and
      for a larger batch a third as many lanes as trajectories, refilled, up to 131,072
      lanes (and within a memory budget).
    - `devices`: how many local devices share the batch; `None`, all of the default
      backend (on CPU one per core: `import rbdyn_jax` starts XLA so, `configure_xla`).
    - `layout`: how each iteration of the loop is laid out: `"cpu"` (for XLA:CPU, whose
      compiled loop runs an iteration as one function: outputs written lane by lane,
      refills only when a lane finished, diffrax's own step), or `"array"` (for a GPU or
      another accelerator, where each operation is a kernel launch and each branch or
      inner loop a wait for the host: one scatter for the outputs, the refill selected
      every iteration, the Runge–Kutta stages unrolled). `None` picks by the devices'
      platform. Both take the same steps and give the same values to round-off.

    A runtime check that fails inside a caller's `jax.jit` (an inertia checked by the
    model's constructor from traced values, say) while the batch runs on several devices
    makes XLA abort the process, after its timeout of about a minute: the device that
    raised leaves the others waiting for it. Check inputs before tracing (NumPy values are
    checked at once), run such a program with `devices=1`, or have equinox give NaN for a
    failed check (`eqx.error_if`). For this reason the lanes run on one device when the
    solve's own checks run at run time: traced output times or tolerances, and
    `throw=True` inside a caller's transformation.

    Needs an explicit Runge–Kutta solver (`diffrax.AbstractERK`: Tsit5, Dopri5, …) and a
    `diffrax.PIDController`; takes no `adjoint`. Same steps and saved values (to
    round-off), `stats` and `result` as `Vmap`. Differentiable in both modes by forward
    sensitivities integrated by the same steps: the cost grows with the differentiated
    parameters per trajectory (6 for an inertia), not with the tangents, and only the
    sensitivities of the state the caller reads are integrated. An inertia is
    differentiated as the symmetric tensor it is (a gradient w.r.t. a raw J is
    (g + gᵀ)/2 of `Vmap`'s g); w.r.t. `ts` the derivative is f(tᵢ, y(tᵢ)), which agrees
    with `Vmap`'s (of its interpolant) to a step's local error. Reverse over reverse is
    refused by JAX's while loop: choose `Vmap` for it.
    """

    lanes: int | None = None
    devices: int | None = None
    layout: str | None = None

    def __check_init__(self):
        _check_counts(self, "lanes", "devices")
        if self.layout is not None and self.layout not in LAYOUTS:
            raise ValueError(f"`layout` must be one of {LAYOUTS} or None, got {self.layout!r}.")

    def solve(
        self, model, y0s, ts, *, solver, controller, adjoint, max_steps, dt0, model_axes
    ) -> Trajectory:
        reason = step_refuse(solver, controller, adjoint)
        if reason is not None:
            raise ValueError(
                f"`Lanes` {reason}; `batching=Vmap()` takes any solver, "
                "controller and adjoint diffeqsolve takes."
            )
        as_nan, mesh, (model, y0s, ts, controller) = _over_devices(
            _lane_solved, self.devices, model, y0s, ts, solver, controller
        )
        platform = mesh.devices.flat[0].platform
        layout = self.layout or default_layout(platform)
        n = jax.tree_util.tree_leaves(y0s)[0].shape[0]
        if self.lanes is None:
            per_lane = lane_bytes(y0s, model if model_axes is not None else None)
            lanes = default_lanes(
                n, mesh.devices.size, platform, per_lane, device_memory(mesh.devices.flat[0])
            )
        else:
            lanes = int(self.lanes)
        # Traced inside a caller's transformation with its checks as NaN (the Program's choice
        # for concrete times and tolerances), with the cache of traced programs on: the
        # loop is stored alone, and the caller's trace holds the stored program.
        stored = as_nan and not top_level() and traces.directory() is not None
        return _lane_solved(
            model,
            y0s,
            ts,
            solver,
            controller,
            max_steps,
            dt0,
            model_axes,
            lanes,
            mesh,
            layout,
            stored,
        )


class Kernel(AbstractBatching):
    """The kernel strategy (`batching=rb.Kernel()`): one Pallas kernel whose every program
    integrates a block of trajectories from start to end, with the solver's own tableau,
    diffrax's `PIDController` rules and the solver's interpolant at `ts`. Same steps,
    accepted/rejected decisions, saved values (to round-off), `stats` and `result` as
    `Vmap` and `Lanes`; a failing trajectory (out of steps, a non-finite start) keeps its
    own code and leaves the others alone.

    **Arguments:**

    - `block`: trajectories a program integrates, a power of two (Triton's blocks are); on
      a GPU a trajectory a thread (`block` / 32 warps, 1 to 32). `None`: 128 on a GPU,
      else the batch (to the next power of two, at most 1024).
    - `interpret`: run the kernel in Pallas's interpret mode (on any platform, slowly);
      `None`: on every platform but a GPU. `False` lowers the kernel through Triton, for a
      GPU: a CPU runs no such kernel (JAX's `ValueError`), though `jax.export` for CUDA
      exports it from one.
    - `devices`: how many local devices share the batch, each running the kernel on its
      share (dealt out in turn, as `Lanes` deals it); `None`: all of them, or the one
      device JAX's `jax.default_device` names where one is set. A trajectory's solve is
      its own whatever device or block it runs in: the same bits for any count.

    The platform is that of JAX's default device: `jax.default_device` where set, else the
    default backend's.

    Needs an explicit Runge–Kutta solver (`diffrax.AbstractERK`), a
    `diffrax.PIDController`, no `adjoint`, and a model whose vector field is written on
    vector components (elementwise arithmetic, slices, stacks, small contractions: the
    models and torques of rbdyn_jax are); a solve it cannot run is refused with a
    `ValueError` naming what. Differentiable in both modes (`jax.grad`, `jax.jacfwd`) as
    `Lanes` is: forward sensitivities integrated in the kernel by the same steps, only
    those of the state the caller reads, an inertia as a symmetric tensor; a second
    derivative is refused (take it through `Lanes` or `Vmap`).
    """

    block: int | None = None
    interpret: bool | None = None
    devices: int | None = None

    def __check_init__(self):
        b = self.block
        if b is not None and (
            isinstance(b, bool) or not isinstance(b, numbers.Integral) or b < 1 or b & (b - 1)
        ):
            raise ValueError(f"`block` must be a power of two or None, got {b!r}.")
        if self.interpret is not None and not isinstance(self.interpret, bool):
            raise ValueError(f"`interpret` must be a bool or None, got {self.interpret!r}.")
        _check_counts(self, "devices")

    def solve(
        self, model, y0s, ts, *, solver, controller, adjoint, max_steps, dt0, model_axes
    ) -> Trajectory:
        reason = step_refuse(solver, controller, adjoint)
        if reason is not None:
            raise ValueError(f"`Kernel` {reason}; `batching=Lanes()` or `Vmap()` takes it.")
        gpu = platform() == "gpu"
        interpret = (not gpu) if self.interpret is None else self.interpret
        run = kernel_interpreted if interpret else kernel_compiled
        # One device where JAX's default device is set: the platform followed is its.
        devices = self.devices
        if devices is None and jax.config.jax_default_device is not None:
            devices = 1
        _, mesh, (model, y0s, ts, controller) = _over_devices(
            run, devices, model, y0s, ts, solver, controller
        )
        n = jax.tree_util.tree_leaves(y0s)[0].shape[0]
        block = kernel_block(self.block, -(-n // mesh.devices.size), gpu)
        return run(
            model, y0s, ts, solver, controller, max_steps, dt0, model_axes, block, interpret, mesh
        )


# Lanes per CPU device: about two trajectories per lane, so that lanes refill and finish
# together, at least a few lanes (a small batch runs side by side), and at most a cap: with
# XLA's loops compiled whole (`configure_xla`) a lane step costs little beyond its
# arithmetic and fewer lanes win; with XLA's defaults the loop's dispatch per iteration is
# shared by more lanes (the performance page).
MAX_LANES_WHOLE, MAX_LANES_DEFAULT, MIN_LANES, PER_LANE = 64, 256, 8, 2
# On an accelerator an iteration costs its kernel launches (dozens of kernels) plus memory
# traffic that grows with the lanes, and an idle lane costs its traffic as a busy one does.
# With a lane per trajectory the loop runs as long as the slowest trajectory while most
# lanes idle (several times the mean steps in the benchmark's batch); refilled lanes,
# `PER_LANE_ARRAY` trajectories each, finish together.
# Below `MIN_LANES_ARRAY` lanes an iteration costs its launches whatever the count, so a
# batch that small gets a lane per trajectory; beyond `MAX_LANES_ARRAY` the launches are a
# small part of an iteration and more lanes only idle longer at the end (measured on the
# performance page). The lanes' working set (`LANE_COPIES` copies of a trajectory's state and
# model arrays: the stages, the dense output, the step's temporaries) stays within
# `MEMORY_SHARE` of the device's memory (`FALLBACK_MEMORY` where the device does not say).
PER_LANE_ARRAY, MIN_LANES_ARRAY, MAX_LANES_ARRAY = 3, 1 << 14, 1 << 17
LANE_COPIES, MEMORY_SHARE, FALLBACK_MEMORY = 64, 0.25, 8 << 30


def default_layout(platform: str) -> str:
    """The lane loop's layout for a device platform: `"cpu"` on a CPU, else `"array"`."""
    return "cpu" if platform == "cpu" else "array"


def lane_bytes(y0s, model=None) -> int:
    """Bytes of one trajectory's state (and model arrays, for a batch of models): the
    leading axis of every array leaf is the batch's."""
    leaves = [x for x in jax.tree_util.tree_leaves((y0s, model)) if eqx.is_array(x)]
    return sum(math.prod(x.shape[1:]) * x.dtype.itemsize for x in leaves)


def device_memory(device) -> int | None:
    """The memory a device's allocator may use, or `None` where it does not say (CPU)."""
    try:
        stats = device.memory_stats()
    except Exception:  # a backend without memory statistics
        return None
    return None if not stats else stats.get("bytes_limit")


def default_lanes(
    n: int, devices: int, platform: str = "cpu", per_lane: int = 0, memory: int | None = None
) -> int:
    """The lanes per device `Lanes()` takes for `n` trajectories over `devices` devices of
    `platform` (a device's `.platform`: "cpu", "gpu", …).

    On a CPU, about two trajectories a lane, at least 8 and at most 64 with XLA's loops
    compiled whole (256 without). On an accelerator, a lane per trajectory of a device's
    share up to 16,384, then a third of the share (refilled), at most 131,072, and at most
    what fits a quarter of `memory` (the device's bytes, `device_memory`; 8 GiB assumed for
    `None`) at 64 copies of `per_lane` bytes a lane (a trajectory's state and model
    arrays; 0 leaves memory out)."""
    share = math.ceil(n / devices)
    if default_layout(platform) == "array":
        budget = MEMORY_SHARE * (memory or FALLBACK_MEMORY)
        fits = int(budget // max(1, LANE_COPIES * per_lane))
        wanted = min(max(math.ceil(share / PER_LANE_ARRAY), MIN_LANES_ARRAY), MAX_LANES_ARRAY)
        return max(1, min(share, wanted, fits))
    cap = MAX_LANES_WHOLE if loops_compiled_whole() else MAX_LANES_DEFAULT
    return max(1, min(cap, max(min(share, MIN_LANES), math.ceil(share / PER_LANE))))


# diffrax's error norm, `PIDController`'s default (the kernel runs it on rows).
DEFAULT_NORM = next(
    f.default for f in dataclasses.fields(diffrax.PIDController) if f.name == "norm"
)


def default_batching(
    solver, controller, adjoint, model=None, y0s=None, model_axes=None, backend=None
) -> AbstractBatching:
    """The default strategy: on a GPU (`backend`, default the platform of JAX's default
    device: `jax.default_device` where set, else the default backend), `Kernel()` where it
    can run the solve (`model` and `y0s` given, its field runs on rows of lanes, and the
    controller measures errors with diffrax's own norm: one of the user's may not run on
    rows); else `Lanes()` where the lane solver can run it; else `Vmap()`."""
    backend = platform() if backend is None else backend
    if (
        backend == "gpu"
        and model is not None
        and y0s is not None
        and step_refuse(solver, controller, adjoint) is None
        and getattr(controller, "norm", DEFAULT_NORM) is DEFAULT_NORM
        and field_refuse(model, y0s, model_axes) is None
    ):
        return Kernel()
    return Vmap() if step_refuse(solver, controller, adjoint) is not None else Lanes()


def _check_counts(strategy, *names):
    """A `ValueError` unless each field `names` of `strategy` is a positive int or None."""
    for name in names:
        v = getattr(strategy, name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1):
            raise ValueError(f"`{name}` must be a positive int or None, got {v!r}.")


def _over_devices(program, devices, model, y0s, ts, solver, controller):
    """How a lane solve or a kernel (`program`) runs over `devices` local devices (`None`:
    all): whether it is traced with its checks as NaN, the mesh, and the inputs placed on
    it (`on_mesh`). One device where the solve checks its times or tolerances at run time,
    since a check raising on one of several devices aborts the process."""
    as_nan = program.checks_nan(model, y0s, ts, solver, controller)
    mesh = _mesh(devices if as_nan else 1)
    if mesh.devices.size > 1:
        model, y0s, ts, controller = on_mesh((model, y0s, ts, controller), mesh)
    return as_nan, mesh, (model, y0s, ts, controller)


def _mesh(devices) -> jax.sharding.Mesh:
    available = jax.local_devices()
    if devices is None:
        devices = len(available)
    if not 1 <= devices <= len(available):
        raise ValueError(
            f"`devices` must be an int in [1, {len(available)}] (the local "
            f"devices), got {devices!r}."
        )
    return device_mesh(available[:devices])


def lane_solve(
    model,
    y0s,
    ts,
    solver,
    controller,
    max_steps,
    dt0,
    model_axes,
    lanes,
    mesh=None,
    layout="cpu",
    stored=False,
) -> Trajectory:
    """The lane loop (`_lane_loop.lane_loop`; on each device of `mesh`, `_dealt.dealt`) and its
    `Trajectory`s, differentiable by forward sensitivities (`_sensitivity.sensitivity_solve`;
    the rule is outside the devices' `shard_map`, which the sensitivities' solve enters as
    the forward solve does).

    `stored`: the loop (and the rule's) is stored alone by the cache of traced programs and
    called as the stored program (`traces.embedded`): for a solve traced inside a caller's
    transformation, whose program rbdyn_jax cannot store."""
    call = traces.embedded if stored else _called
    batched = model_axes is not None

    def loop(system, y0s, ts, tols, cstatic):
        return call(
            lane_run,
            system,
            y0s,
            ts,
            tols,
            cstatic,
            solver,
            max_steps,
            dt0,
            batched,
            lanes,
            mesh,
            layout,
        )

    return sensitivity_solve(loop, model, y0s, ts, controller, model_axes)


def _called(fn, *args):
    return fn(*args)


def lane_run(
    system, y0s, ts, tols, cstatic, solver, max_steps, dt0, batched, lanes, mesh, layout="cpu"
):
    """The lane loop (in `layout`), on one device or on each of `mesh`'s."""
    run = functools.partial(
        lane_loop,
        solver=solver,
        max_steps=max_steps,
        dt0=dt0,
        batched=batched,
        lanes=lanes,
        layout=layout,
    )
    if mesh is None or mesh.devices.size == 1:
        return run(system, y0s, ts, eqx.combine(tols, cstatic))
    return dealt(run, system, y0s, ts, tols, cstatic, batched, mesh)


_vmapped = Program(solve_vmapped, validated=checked_before_tracing)
_lane_solved = Program(lane_solve, validated=checked_before_tracing)
