"""rbdyn_jax: differentiable rotational dynamics of rigid bodies in JAX.

Conventions (PHYSICS.md §1): quaternions are Hamilton, scalar first `[w, x, y, z]`;
`R(q)` maps body components to parent components; Euler sequences follow
`scipy.spatial.transform.Rotation` (upper case intrinsic, lower case extrinsic).
The library never switches on float64: call `jax.config.update("jax_enable_x64", True)`.
"""

from . import (
    dynamics as dynamics,
    frames as frames,
    inertia as inertia,
    invariants as invariants,
    models as models,
    rotation as rotation,
    torques as torques,
)
from .frames import (
    AbstractFrame as AbstractFrame,
    CircularOrbit as CircularOrbit,
    ConstantRate as ConstantRate,
    EulerAngleFrame as EulerAngleFrame,
    Inertial as Inertial,
)
from .integrate import (
    RESULTS as RESULTS,
    Trajectory as Trajectory,
    simulate as simulate,
    simulate_batch as simulate_batch,
)
from .models import (
    AbstractRigidBody as AbstractRigidBody,
    EulerAngleRigidBody as EulerAngleRigidBody,
    PoissonRigidBody as PoissonRigidBody,
    RelativeRigidBody as RelativeRigidBody,
    RigidBody as RigidBody,
)
from .state import (
    EulerState as EulerState,
    Kinematics as Kinematics,
    PoissonState as PoissonState,
    State as State,
)
from .torques import (
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

__version__ = "0.1.0"
