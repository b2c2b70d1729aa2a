"""The kernel strategy's entry: `kernel_solve`, the kernel (`_kernel_run.kernel_run`) over
a batch and its `Trajectory`s, differentiable once by forward sensitivities
(`_sensitivity.lane_jvp`, the lane solver's rule), and the two `Program`s `Kernel.solve`
calls: `kernel_compiled` (the kernel lowered for a GPU) and `kernel_interpreted` (Pallas's
interpret mode, compiled at a lower XLA optimisation level).
"""

import functools

import equinox as eqx
import jax

from .._program.program import Program
from .._program.xla import COMPILER_OPTIONS
from ._field import checked_before_tracing, checked_times, finish, promoted
from ._kernel_run import kernel_run
from ._lane_system import Plain
from ._sensitivity import lane_jvp
from ._solution import Trajectory, as_result


def kernel_solve(
    model, y0s, ts, solver, controller, max_steps, dt0, model_axes, block, interpret
) -> Trajectory:
    """The kernel (`Kernel`) over the batch, and its `Trajectory`s.

    Differentiable in both modes by forward sensitivities, by the lane solver's rule
    (`_sensitivity.lane_jvp`, see `_batching.lane_solve`): the kernel integrates the model
    extended by the variational equations (`_sensitivity.Sensitivity`, whose field is one
    `jax.jvp` of the model's, run on rows as the field is) by the same steps, for the
    state leaves the caller reads only, and the rule contracts them with the tangents. A
    derivative of that derivative is refused."""
    ts = checked_times(ts)
    batched = model_axes is not None
    if batched:  # every array leaf with a leading trajectory axis
        model = eqx.filter_vmap(lambda m: m, in_axes=(model_axes,))(model)
    dyn, static = eqx.partition(model, eqx.is_array)
    y0s = promoted(dyn, y0s, ts)
    tols, cstatic = eqx.partition(controller, eqx.is_array)

    def loop(system, y0s, ts, tols):
        return kernel_run(
            system,
            y0s,
            ts,
            eqx.combine(tols, cstatic),
            solver,
            max_steps,
            dt0,
            batched,
            block,
            interpret,
        )

    @jax.custom_jvp
    def solve(dyn, y0s, ts, tols):
        return loop(Plain(eqx.combine(dyn, static)), y0s, ts, tols)

    solve.defjvp(functools.partial(lane_jvp, loop, static, batched), symbolic_zeros=True)
    ys, ok0, result, counts = solve(dyn, y0s, ts, tols)

    def finished(m, ys, ok, result, counts):
        return finish(m, ts, ys, ok, as_result(result), list(counts))

    return eqx.filter_vmap(finished, in_axes=(0 if batched else None, 0, 0, 0, 0))(
        model, ys, ok0, result, counts
    )


# In interpret mode (a CPU: for checking, not for speed) the kernel is thousands of
# operations on rows, which XLA compiles markedly faster at its backend optimisation level
# 1 than at its default. Level 0 would be faster still, but rounds some float32 operations
# otherwise than `Vmap`'s program, and the steps would then differ. A Pallas program is not
# stored by the cache of traced programs (`jax.export` does not serialize it).
INTERPRET_OPTIONS = {**COMPILER_OPTIONS, "xla_backend_optimization_level": 1}
kernel_compiled = Program(kernel_solve, validated=checked_before_tracing, store=False)
kernel_interpreted = Program(
    kernel_solve, validated=checked_before_tracing, options=INTERPRET_OPTIONS, store=False
)
