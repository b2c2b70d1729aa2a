"""rbdyn_jax: differentiable rotational dynamics of rigid bodies in JAX.

Conventions (docs/physics.md#conventions): quaternions are Hamilton, scalar first `[w, x, y, z]`;
`R(q)` maps body components to parent components; Euler sequences follow
`scipy.spatial.transform.Rotation` (upper case intrinsic, lower case extrinsic).
The library never switches on float64: call `jax.config.update("jax_enable_x64", True)`.
"""

from . import (
    analytic as analytic,
)
from . import (
    dynamics as dynamics,
)
from . import (
    frames as frames,
)
from . import (
    identify as identify,
)
from . import (
    inertia as inertia,
)
from . import (
    integrate as integrate,
)
from . import (
    invariants as invariants,
)
from . import (
    models as models,
)
from . import (
    rotation as rotation,
)
from . import (
    scenario as scenario,
)
from . import (
    sweep as sweep,
)
from . import (
    torques as torques,
)
from ._version import __version__ as __version__
from .frames import (
    AbstractFrame as AbstractFrame,
)
from .frames import (
    CircularOrbit as CircularOrbit,
)
from .frames import (
    ConstantRate as ConstantRate,
)
from .frames import (
    EulerAngleFrame as EulerAngleFrame,
)
from .frames import (
    HarmonicAngles as HarmonicAngles,
)
from .frames import (
    Inertial as Inertial,
)
from .integrate import (
    COMPILER_OPTIONS as COMPILER_OPTIONS,
)
from .integrate import (
    RESULTS as RESULTS,
)
from .integrate import (
    AbstractBatching as AbstractBatching,
)
from .integrate import (
    Lanes as Lanes,
)
from .integrate import (
    Trajectory as Trajectory,
)
from .integrate import (
    Vmap as Vmap,
)
from .integrate import (
    configure_xla as configure_xla,
)
from .integrate import (
    simulate as simulate,
)
from .integrate import (
    simulate_batch as simulate_batch,
)
from .models import (
    AbstractRigidBody as AbstractRigidBody,
)
from .models import (
    EulerAngleRigidBody as EulerAngleRigidBody,
)
from .models import (
    PoissonRigidBody as PoissonRigidBody,
)
from .models import (
    RelativeRigidBody as RelativeRigidBody,
)
from .models import (
    RigidBody as RigidBody,
)
from .models import (
    with_log_cholesky as with_log_cholesky,
)
from .state import (
    EulerState as EulerState,
)
from .state import (
    Kinematics as Kinematics,
)
from .state import (
    PoissonState as PoissonState,
)
from .state import (
    State as State,
)
from .torques import (
    AbstractTorque as AbstractTorque,
)
from .torques import (
    BalancingTransport as BalancingTransport,
)
from .torques import (
    BodyTorque as BodyTorque,
)
from .torques import (
    GravityGradient as GravityGradient,
)
from .torques import (
    InertialTorque as InertialTorque,
)
from .torques import (
    NoTorque as NoTorque,
)
from .torques import (
    PolynomialSinPsi as PolynomialSinPsi,
)
from .torques import (
    RestoringMoment as RestoringMoment,
)
from .torques import (
    SumTorque as SumTorque,
)
from .torques import (
    UniformGravity as UniformGravity,
)
