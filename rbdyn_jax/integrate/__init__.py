"""Integration of a model with diffrax: the solves, their batching strategies and solvers.

`simulate(model, y0, ts, ...)` solves one trajectory; `simulate_batch(model, y0s, ts, ...)`
a batch, over initial conditions and, with `model_axes`, model parameters, by a batching
strategy (`Kernel`, one Pallas kernel integrating a block of trajectories a program;
`Lanes`, the lane solver; or `Vmap`, `diffeqsolve` vmapped; the default picks the fastest
that can run the solve on the backend). Both are compiled once per model *structure*.

The modules, one idea each:

- `_solution`: what a solve returns (`Trajectory`, `RESULTS`);
- `_field`: the vector-field plumbing every solve shares (unit time, guarded field, start
  checks, the finished `Trajectory`);
- `_simulate`: the public `simulate` and `simulate_batch` and their input checks;
- `_diffeqsolve`: one trajectory by `diffrax.diffeqsolve`, and its vmapped batch;
- `_batching`: the strategies `Vmap`, `Lanes` and `Kernel`, and the default;
- `_lane_loop`: the lane loop and its typed state;
- `_lane_system`: what the lane loop and the kernel integrate (the model, or the model and
  its sensitivities), and its field over a set of lanes;
- `_lane_step`: one trajectory's start, Runge–Kutta step and step-size control, shared by
  the lane loop and the kernel;
- `_lane_arrays`: per-lane selects, takes and writes on the lane loop's arrays, and the
  interpolant of every lane's last step;
- `_kernel_solve`: the kernel strategy's solve, its derivative and its two programs;
- `_kernel_run`: the Pallas kernel that integrates a block of trajectories per program;
- `_kernel_layout`: the kernel's blocks of lanes and its pytrees as rows of lanes;
- `_kernel_refusal`: the solves and models the kernel cannot run, by name;
- `_rows`: a one-trajectory function run on rows of lanes (the kernel's arithmetic);
- `_sensitivity`: forward sensitivities, the derivative rule of the lane loop and the kernel;
- `_dependencies`: which state leaves a derivative must carry;
- `_lie_poisson`: `LiePoissonSplitting`, the structure-preserving solver of the rigid body
  (exact flows of the kinetic energy's terms, potential torques as kicks), with
  `_splittable`, the models, torques and fixed steps it takes; `_exact_flows`, the
  principal frame and the exact flows as compensated increments; `_splitting_step`, one
  composed step (`Stepper`); and `_composition`, the symmetric compositions that raise it
  to orders 4 and 6;
- `_cheapest`: the equation that runs the cheapest program giving what is read.

Each solve is compiled as a `Program` of the compile layer (`rbdyn_jax/_program/`): once
per input structure, its checks as NaN where the times and tolerances were checked before
tracing, and its trace then stored by the layer's cache of traced programs.

Every use of diffrax's, equinox's or JAX's internals is in `rbdyn_jax/_compat.py`, except
the jaxpr parameters `_rows` reads to replay a trace (a scan's counts, a call's jaxpr),
which tests/test_rows.py checks against `jax.vmap` under the pinned and the next JAX.

`COMPILER_OPTIONS` are the XLA options of every program rbdyn_jax compiles. Pass them to
your own `jax.jit` around a solve: `jax.jit(jax.grad(loss), compiler_options=
COMPILER_OPTIONS)`. `configure_xla()` sets XLA's process-wide flags for faster solves on
CPU, before JAX computes anything; `import rbdyn_jax` calls it (one device per core) unless
`RBDYN_JAX_CONFIGURE_XLA=0`.
"""

from .._program.xla import COMPILER_OPTIONS as COMPILER_OPTIONS, configure_xla as configure_xla
from ._batching import (
    AbstractBatching as AbstractBatching,
    Kernel as Kernel,
    Lanes as Lanes,
    Vmap as Vmap,
    default_batching as default_batching,
    default_lanes as default_lanes,
    device_memory as device_memory,
)
from ._lie_poisson import ORDERS as SPLITTING_ORDERS, LiePoissonSplitting as LiePoissonSplitting
from ._simulate import (
    MAX_STEPS as MAX_STEPS,
    default_tolerance as default_tolerance,
    make_controller as make_controller,
    min_rtol as min_rtol,
    simulate as simulate,
    simulate_batch as simulate_batch,
)
from ._solution import (
    RESULTS as RESULTS,
    Trajectory as Trajectory,
    result_code as result_code,
    result_names as result_names,
)
from ._splittable import fixed_steps as fixed_steps

__all__ = [
    "COMPILER_OPTIONS",
    "MAX_STEPS",
    "RESULTS",
    "SPLITTING_ORDERS",
    "AbstractBatching",
    "Kernel",
    "Lanes",
    "LiePoissonSplitting",
    "Trajectory",
    "Vmap",
    "configure_xla",
    "default_batching",
    "default_lanes",
    "default_tolerance",
    "device_memory",
    "fixed_steps",
    "make_controller",
    "min_rtol",
    "result_code",
    "result_names",
    "simulate",
    "simulate_batch",
]
