"""The kernel strategy's entry: `kernel_solve`, the kernel (`_kernel_run.kernel_run`) over
a batch and its `Trajectory`s, differentiable once by forward sensitivities (the lane
solver's rule, `_sensitivity.sensitivity_solve`), and the two `Program`s `Kernel.solve`
calls: `kernel_compiled` (the kernel lowered for a GPU) and `kernel_interpreted` (Pallas's
interpret mode, compiled at a lower XLA optimisation level).
"""

import equinox as eqx

from .._program.program import Program
from .._program.xla import COMPILER_OPTIONS
from ._dealt import dealt
from ._field import checked_before_tracing
from ._kernel_run import kernel_run
from ._sensitivity import sensitivity_solve
from ._solution import Trajectory


def kernel_solve(
    model, y0s, ts, solver, controller, max_steps, dt0, model_axes, block, interpret, mesh=None
) -> Trajectory:
    """The kernel (`Kernel`) over the batch (on each device of `mesh`, its share dealt out:
    `_dealt.dealt`), and its `Trajectory`s.

    Differentiable in both modes by forward sensitivities, by the lane solver's rule
    (`_sensitivity.sensitivity_solve`): the kernel integrates the model extended by the
    variational equations (`_sensitivity.Sensitivity`, whose field is one `jax.jvp` of the
    model's, run on rows as the field is) by the same steps, for the state leaves the
    caller reads only, and the rule contracts them with the tangents. A derivative of that
    derivative is refused."""
    batched = model_axes is not None

    def run(system, y0s, ts, controller):
        return kernel_run(
            system, y0s, ts, controller, solver, max_steps, dt0, batched, block, interpret
        )

    def loop(system, y0s, ts, tols, cstatic):
        if mesh is None or mesh.devices.size == 1:
            return run(system, y0s, ts, eqx.combine(tols, cstatic))
        return dealt(run, system, y0s, ts, tols, cstatic, batched, mesh)

    return sensitivity_solve(loop, model, y0s, ts, controller, model_axes)


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
