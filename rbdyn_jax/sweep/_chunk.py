"""The compiled chunk solver: a chunk of a scenario's trajectories sampled and solved in one
program, over the local devices.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding

from .._program.devices import BATCH, mesh as device_mesh, over_devices
from .._program.program import Program
from .._program.xla import jit
from ..integrate import (
    RESULTS,
    Kernel,
    Lanes,
    Vmap,
    default_batching,
    result_code,
    simulate_batch,
)
from ..scenario import SUMMARIES, Scenario


def _solve_block(scenario: Scenario, dists, key, idx, lanes):
    """Sample and solve the trajectories `idx` (through `lanes` lanes of the lane solver);
    per-trajectory outputs."""
    values = jax.vmap(lambda i: scenario.sample(dists, key, i))(idx)
    # A non-finite draw (an overflowing lognormal, …) would fail the model's checks for the
    # whole block: solve the nominal values in its lane instead and mark it non-finite.
    ok = jnp.ones(idx.shape, bool)
    for v in values.values():
        ok = ok & jnp.all(jnp.isfinite(v.reshape(v.shape[0], -1)), axis=-1)
    nominal = {p: d.centre() for p, d in dists.items()}

    def lane(x):
        return ok.reshape((-1,) + (1,) * (x.ndim - 1))

    values = {p: jnp.where(lane(v), v, nominal[p]) for p, v in values.items()}
    models, y0s = jax.vmap(scenario.build)(values)
    # The scenario's times and tolerances are constants of the trace: the solve is then
    # traced with its checks as NaN (its inputs validated), and its loops can be stored.
    traj = simulate_batch(
        models,
        y0s,
        scenario.ts,
        model_axes=0,
        solver=scenario.diffrax_solver,
        stepsize_controller=scenario.stepsize_controller,
        dt0=scenario.dt,
        max_steps=scenario.max_steps,
        batching=_batching(scenario, models, y0s, lanes),
    )
    status = jnp.where(ok, result_code(traj.result), result_code(RESULTS.nonfinite_state))

    def summaries(m, tr):
        return {name: SUMMARIES[name].fn(m, tr) for name in scenario.summaries}

    summ = jax.vmap(summaries)(models, traj)
    good = status == 0
    out = {"omega": traj.ys.omega, "quat": traj.ys.quat, "inertia": models.inertia}
    out = {
        k: jnp.where(lane(v) if k == "inertia" else good[:, None, None], v, jnp.nan)
        for k, v in out.items()
    }
    return {
        **out,
        "status": status.astype(jnp.int32),
        "num_steps": traj.stats["num_steps"].astype(_index_dtype()),
        **{k: jnp.where(good, v, jnp.nan) for k, v in summ.items()},
    }


def _batching(scenario: Scenario, models, y0s, lanes):
    """How a block is solved: `Vmap` for a fixed-step method (`LiePoissonSplitting` steps
    every trajectory in lockstep, so `Vmap` wastes nothing, and the lane solver and the
    kernel take only adaptive Runge–Kutta methods); `Kernel` where `simulate_batch`'s
    default takes it (a GPU backend, and the scenario's model field runs on rows of lanes);
    else the lane solver through `lanes` lanes; either on the block's device. A kernel's trajectory
    is integrated by its own lane of a program, its arithmetic the same whatever the other
    lanes hold, so a sweep's bits do not depend on its chunking either way."""
    if scenario.fixed_step:
        return Vmap()
    chosen = default_batching(
        scenario.diffrax_solver, scenario.stepsize_controller, None, models, y0s, model_axes=0
    )
    if isinstance(chosen, Kernel):
        return dataclasses.replace(chosen, devices=1)
    return Lanes(lanes, devices=1)


_PER_LANE = 8  # trajectories per lane in one CPU block (a block: 8 × lanes)
_STATES = ("omega", "quat")  # the variables `trajectories` keeps all, some or none of


def _index_dtype():
    """Integers in the program: int64 with 64-bit types enabled, else int32."""
    return jax.dtypes.canonicalize_dtype(np.int64)


def _quantum(platform: str, lanes: int) -> int:
    """What a device's share of a chunk is a multiple of: its blocks of 8 × `lanes` on a
    CPU, where a device runs its share through the same block program one block after the
    other; one trajectory on an accelerator, where one block takes the whole share at once
    (through `lanes` lanes, refilled)."""
    return _PER_LANE * lanes if platform == "cpu" else 1


def _chunk_program(sc: Scenario, lanes: int, mesh, idx, key) -> dict:
    """Sample and solve the trajectories `idx` (sharded over `mesh`'s devices) of the
    scenario `sc`, a pytree whose leaves are its distributions' parameters.

    The scenario's structure is static and exactly described by its source, so the cache
    of traced programs can store the program: a later process with the cache configured
    loads it instead of tracing it. Traced with the solves' checks as NaN (a `Program` of
    validated inputs: the scenario was validated, and a failing trajectory is reported in
    `status`), so the program holds no host callback and can be stored."""
    dists = sc.dists
    quantum = _quantum(mesh.devices.flat[0].platform, lanes)

    def per_device(idx, dists, key):
        block = idx.shape[0] if quantum == 1 else quantum
        # On a CPU, fixed blocks, one after the other: the block's program is then the same
        # for every chunk size and device count, so the results are bitwise identical
        # across them (a lane-solver loop over the whole share compiles differently for
        # each share size and rounds differently). Fixed blocks also avoid a hang in the
        # XLA runtime (all threads asleep) that one loop over a large share (2048 on 2
        # XLA:CPU host devices) runs into. On an accelerator, one block: the device's
        # whole share through `lanes` lanes, refilled.
        out = jax.lax.map(lambda b: _solve_block(sc, dists, key, b, lanes), idx.reshape(-1, block))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    # No collectives inside the solver loop: each device runs its own while loops.
    sharded = over_devices(per_device, mesh, (True, False, False))
    # A float32 sweep's matrix products (the energies' `einsum`s, …) in full float32: at
    # JAX's default precision, NVIDIA GPUs since Ampere take them in TF32 (a 10-bit
    # mantissa), errors of 1e-4 in a float32 sweep's energy drifts where float32 gives 1e-6.
    precision = (
        jax.default_matmul_precision("highest")
        if sc.dtype == "float32"
        else contextlib.nullcontext()
    )
    with precision:
        return sharded(idx, dists, key)


_solve_chunk = Program(_chunk_program)


@jit
def _take(states, pos):
    """The rows `pos` of each array of `states`: a K store's sampled states, gathered on the
    device so that only they are copied to the host."""
    return [x[pos] for x in states]


@dataclasses.dataclass
class _Runner:
    """The compiled chunk solver: every call has the same padded size (one compilation)."""

    scenario: Scenario
    lanes: int
    devices: list
    chunk: int
    mesh: Any = dataclasses.field(init=False)
    solved: Scenario = dataclasses.field(init=False)  # what the chunk program solves

    def __post_init__(self):
        self.mesh = device_mesh(self.devices)
        # Which states a store keeps is chosen after the solve: stores keeping all, some or
        # none of them run one program, and hold the same bits.
        self.solved = self.scenario.with_settings(trajectories="all")

    @property
    def size(self) -> int:
        """The padded chunk: a multiple of the block (`_block`) × devices."""
        quantum = _quantum(self.devices[0].platform, self.lanes) * len(self.devices)
        return -(-self.chunk // quantum) * quantum

    @property
    def every(self) -> int | None:
        """K of a store keeping every K-th trajectory's states, else `None`."""
        keep = self.scenario.trajectories
        return keep if isinstance(keep, int) else None

    def launch(self, idx: np.ndarray, key) -> dict:
        """Start solving the trajectories `idx` (≤ chunk of them) and return at once: JAX
        dispatches the program and hands back its outputs before they are computed. The
        states the store does not keep are dropped on the device."""
        n = len(idx)  # padded with copies of the last index (solved, then dropped)
        full = np.concatenate([idx, np.full(self.size - n, idx[-1], idx.dtype)])
        full = full.astype(_index_dtype())
        arr = jax.make_array_from_callback(
            (self.size,), NamedSharding(self.mesh, BATCH), lambda i: full[i]
        )
        out = dict(_solve_chunk(self.solved, self.lanes, self.mesh, arr, key))
        states = [out.pop(k) for k in _STATES]
        if self.scenario.trajectories == "all":
            out.update(zip(_STATES, states))
        elif self.every is not None:
            # At most ceil(size / K) multiples of K among ≤ size consecutive indices: a
            # fixed number of rows, so the gather compiles once.
            pos = np.flatnonzero(idx % self.every == 0)
            pos = np.concatenate(
                [pos, np.zeros(-(-self.size // self.every) - pos.size, pos.dtype)]
            ).astype(_index_dtype())
            out.update(zip(_STATES, _take(states, pos)))
        return out

    def collect(self, out: dict, idx: np.ndarray) -> dict[str, np.ndarray]:
        """The outputs of `launch` for its trajectories `idx` (waits for them)."""
        sampled = idx.size if self.every is None else int(np.sum(idx % self.every == 0))
        return {k: np.asarray(v)[: sampled if k in _STATES else idx.size] for k, v in out.items()}


_RUNNERS: dict[tuple, _Runner] = {}


def _runner(sc: Scenario, lanes: int, devices: tuple, chunk: int) -> _Runner:
    """A compiled runner, reused by later runs of the same scenario and layout (a resumed
    or repeated run in the same process compiles nothing)."""
    quantum = _quantum(devices[0].platform, lanes) * len(devices)  # the compiled shape
    key = (json.dumps(sc.source, sort_keys=True), lanes, devices, -(-chunk // quantum))
    if key not in _RUNNERS:
        _RUNNERS.clear()  # keep one
        _RUNNERS[key] = _Runner(sc, lanes, list(devices), chunk)
    return _RUNNERS[key]
