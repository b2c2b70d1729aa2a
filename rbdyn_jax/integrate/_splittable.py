"""Which models, torques and step-size controllers `LiePoissonSplitting` takes, checked
before a solve is traced: a `RigidBody` whose torque depends on the attitude alone (an exact
kick), fixed steps of a positive `dt0`, and a `max_steps` that covers the times.
"""

import math

import diffrax
import jax
import numpy as np

from ..models import RigidBody
from ..torques import (
    BodyTorque,
    GravityGradient,
    InertialTorque,
    NoTorque,
    RestoringMoment,
    SumTorque,
    UniformGravity,
)

# The torques whose moment depends on the attitude (and, for the restoring moment, on time
# through its slow time τ = ε t) alone: the flow of L' = M(t, q), q' = 0 is the exact kick
# L ← L + h M. `NoTorque` adds nothing. Exact classes, not subclasses: a subclass may
# depend on the rates. Uniform gravity and the gravity gradient derive from a potential
# (the method is then symplectic, its energy error bounded); the others have none, and the
# method keeps its order, |q| and the free flows' structure but no energy.
KICKED = (UniformGravity, GravityGradient, RestoringMoment, BodyTorque, InertialTorque)


def _refusal(what: str) -> str:
    return (
        f"`LiePoissonSplitting` cannot integrate {what} geometrically: it splits a "
        "`RigidBody` whose torque depends on the attitude alone (`NoTorque`, "
        "`UniformGravity`, `GravityGradient`, `RestoringMoment`, `BodyTorque`, "
        "`InertialTorque` and their sums), which acts as an exact kick. Use an adaptive "
        "solver for this model: the default `diffrax.Tsit5()`, or `diffrax.Dopri8()` "
        "with tight tolerances (docs/physics.md#what-the-splitting-cannot-treat)."
    )


def check_splittable(model) -> bool:
    """Whether `model` has a torque to kick with (False: torque-free); a `ValueError`
    naming the model or the torque where the splitting cannot treat it."""
    if type(model) is not RigidBody:
        name = type(model).__name__
        raise ValueError(
            _refusal(
                f"a `{name}`, a subclass of `RigidBody` whose equations it does not know"
                if isinstance(model, RigidBody)
                else f"a `{name}` (the relative-motion equations and the Euler-angle and Poisson "
                "state forms have no such split)"
            )
        )
    parts = model.torque.torques if isinstance(model.torque, SumTorque) else (model.torque,)
    kicked = False
    for torque in parts:
        if type(torque) is NoTorque:
            continue
        if type(torque) not in KICKED:
            raise ValueError(
                _refusal(
                    f"the torque `{type(torque).__name__}` (a moment that depends on the rates, "
                    "or one whose dependence the splitting does not know, has no exactly solved "
                    "flow of its own)"
                )
            )
        kicked = True
    return kicked


def fixed_steps(span: float, dt: float) -> int:
    """The steps of `dt` that cover `span`: ⌈span / dt⌉, a quotient within rounding of a
    whole number counting as that number (a last step that rounding would leave shorter
    than 1e-12 of `dt` is not one)."""
    return math.ceil(span / dt * (1.0 - 1e-12))


def fixed_step_controller(model, ts, controller, rtol, atol, dt0, max_steps):
    """The step-size controller of a `LiePoissonSplitting` solve, checked before it is
    traced: the model and its torque (`check_splittable`), no tolerances, a fixed-step
    controller (`diffrax.ConstantStepSize()` where none is given, or `diffrax.StepTo`), a
    positive `dt0` for `ConstantStepSize`, and, where `ts` and `dt0` are concrete, a
    `max_steps` that covers `ts` in steps of `dt0`."""
    check_splittable(model)
    if rtol is not None or atol is not None:
        raise ValueError(
            "`LiePoissonSplitting` takes fixed steps (`dt0`): `rtol` and `atol` "
            "mean nothing to it; leave them out."
        )
    if controller is None:
        controller = diffrax.ConstantStepSize()
    if not isinstance(controller, (diffrax.ConstantStepSize, diffrax.StepTo)):
        raise ValueError(
            "`LiePoissonSplitting` takes fixed steps: `stepsize_controller` "
            "must be `diffrax.ConstantStepSize()` (the default, with `dt0`) or "
            f"`diffrax.StepTo(ts)`, got {type(controller).__name__}."
        )
    if isinstance(controller, diffrax.StepTo):
        return controller
    if dt0 is None:
        raise ValueError(
            "`dt0` is the fixed step of `LiePoissonSplitting`: give it (in the "
            "unit of `ts`; a fiftieth to a hundredth of the motion's period "
            "suits order 6, docs/physics.md#choosing-the-step)."
        )
    if isinstance(dt0, jax.core.Tracer) or isinstance(ts, jax.core.Tracer):
        return controller
    if not float(dt0) > 0:
        raise ValueError(f"`dt0` must be a positive step, got {dt0!r}.")
    t = np.asarray(ts)
    steps = fixed_steps(float(t[-1]) - float(t[0]), float(dt0))
    if max_steps < steps:
        raise ValueError(
            f"`max_steps` = {max_steps} is fewer than the {steps} steps of "
            f"`dt0` = {float(dt0):g} from ts[0] to ts[-1]: give `max_steps` ≥ "
            f"{steps}."
        )
    return controller
