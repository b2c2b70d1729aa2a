"""rbdyn_jax: differentiable rotational dynamics of rigid bodies in JAX.

Conventions (docs/physics.md#conventions): quaternions are Hamilton, scalar first `[w, x, y, z]`;
`R(q)` maps body components to parent components; Euler sequences follow
`scipy.spatial.transform.Rotation` (upper case intrinsic, lower case extrinsic).
The library never switches on float64: call `jax.config.update("jax_enable_x64", True)`.
"""

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
    sweep as sweep,
    torques as torques,
)
from ._version import __version__ as __version__
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
    Lanes as Lanes,
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
