"""rbdyn_jax: differentiable rotational dynamics of rigid bodies in JAX.

Conventions (docs/physics.md#conventions): quaternions are Hamilton, scalar first `[w, x, y, z]`;
`R(q)` maps body components to parent components; Euler sequences follow
`scipy.spatial.transform.Rotation` (upper case intrinsic, lower case extrinsic).
The library never switches on float64: call `jax.config.update("jax_enable_x64", True)`.

Importing the package imports no JAX: each submodule, and each name exported here, is
imported when first used. The import sets XLA's flags for the solves, unless
`RBDYN_JAX_CONFIGURE_XLA=0` (`configure_xla`, docs/guide/batches.md).
"""

import importlib as _importlib
from typing import TYPE_CHECKING

from ._program.flags import configure_on_import as _configure_on_import
from ._version import __version__ as __version__

if TYPE_CHECKING:  # what the lazy names below resolve to, for type checkers and IDEs
    from . import (
        analytic as analytic,
        dynamics as dynamics,
        frames as frames,
        identify as identify,
        inertia as inertia,
        integrate as integrate,
        invariants as invariants,
        models as models,
        rotation as rotation,
        scenario as scenario,
        state as state,
        sweep as sweep,
        torques as torques,
    )
    from .frames import (
        AbstractFrame as AbstractFrame,
        CircularOrbit as CircularOrbit,
        ConstantRate as ConstantRate,
        EulerAngleFrame as EulerAngleFrame,
        HarmonicAngles as HarmonicAngles,
        Inertial as Inertial,
    )
    from .integrate import (
        COMPILER_OPTIONS as COMPILER_OPTIONS,
        RESULTS as RESULTS,
        AbstractBatching as AbstractBatching,
        Kernel as Kernel,
        Lanes as Lanes,
        LiePoissonSplitting as LiePoissonSplitting,
        Trajectory as Trajectory,
        Vmap as Vmap,
        configure_xla as configure_xla,
        simulate as simulate,
        simulate_batch as simulate_batch,
    )
    from .models import (
        AbstractRigidBody as AbstractRigidBody,
        EulerAngleRigidBody as EulerAngleRigidBody,
        PoissonRigidBody as PoissonRigidBody,
        RelativeRigidBody as RelativeRigidBody,
        RigidBody as RigidBody,
        with_log_cholesky as with_log_cholesky,
    )
    from .state import (
        EulerState as EulerState,
        Kinematics as Kinematics,
        PoissonState as PoissonState,
        State as State,
    )
    from .torques import (
        AbstractConservativeTorque as AbstractConservativeTorque,
        AbstractTorque as AbstractTorque,
        BalancingTransport as BalancingTransport,
        BodyTorque as BodyTorque,
        GravityGradient as GravityGradient,
        InertialTorque as InertialTorque,
        NoTorque as NoTorque,
        PolynomialSinPsi as PolynomialSinPsi,
        RestoringMoment as RestoringMoment,
        SumTorque as SumTorque,
        UniformGravity as UniformGravity,
    )

# The same modules and names as the block above (tests/test_package.py checks it).
_SUBMODULES = (
    "analytic",
    "dynamics",
    "frames",
    "identify",
    "inertia",
    "integrate",
    "invariants",
    "models",
    "rotation",
    "scenario",
    "state",
    "sweep",
    "torques",
)
_EXPORTS = {
    "frames": (
        "AbstractFrame",
        "CircularOrbit",
        "ConstantRate",
        "EulerAngleFrame",
        "HarmonicAngles",
        "Inertial",
    ),
    "integrate": (
        "COMPILER_OPTIONS",
        "RESULTS",
        "AbstractBatching",
        "Kernel",
        "Lanes",
        "LiePoissonSplitting",
        "Trajectory",
        "Vmap",
        "configure_xla",
        "simulate",
        "simulate_batch",
    ),
    "models": (
        "AbstractRigidBody",
        "EulerAngleRigidBody",
        "PoissonRigidBody",
        "RelativeRigidBody",
        "RigidBody",
        "with_log_cholesky",
    ),
    "state": ("EulerState", "Kinematics", "PoissonState", "State"),
    "torques": (
        "AbstractConservativeTorque",
        "AbstractTorque",
        "BalancingTransport",
        "BodyTorque",
        "GravityGradient",
        "InertialTorque",
        "NoTorque",
        "PolynomialSinPsi",
        "RestoringMoment",
        "SumTorque",
        "UniformGravity",
    ),
}
_ORIGIN = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_ORIGIN)


def __getattr__(name: str):
    """A submodule or an exported name, imported on first use (PEP 562) and kept."""
    if name in _SUBMODULES:
        return _importlib.import_module(f"{__name__}.{name}")  # sets the attribute itself
    if name in _ORIGIN:
        value = getattr(_importlib.import_module(f"{__name__}.{_ORIGIN[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_SUBMODULES, *__all__})


_configure_on_import()
