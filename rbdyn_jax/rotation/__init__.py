"""Attitude kinematics: quaternions, direction-cosine matrices, Euler/Cardan angles.

Conventions (docs/physics.md#quaternions, docs/physics.md#euler-angles): Hamilton quaternions,
scalar first `[w, x, y, z]`; `R(q)` maps body components to parent components,
`v_parent = R(q) v_body`; Euler sequences exactly as `scipy.spatial.transform.Rotation`: upper
case ("ZXZ") intrinsic, rotations about the moving axes, `R = R_a(α) R_b(β) R_c(γ)`; lower case
("zxz") extrinsic, about the fixed axes, so that "abc" with angles (α, β, γ) is intrinsic "CBA"
with angles (γ, β, α).

Every function is pure, accepts leading `*batch` axes and is safe under `jit`, `vmap` and
`grad`: singular branches use a double `where` (a safe argument in the branch not taken) and
Taylor series near zero, so that values and gradients stay finite there.

The modules, one idea each:

- `_quaternion`: quaternion algebra and the conversions between a quaternion and its
  rotation matrix, `quat_multiply`, `quat_conjugate`, `quat_normalize`, `quat_rotate`,
  `quat_to_dcm` and `dcm_to_quat`;
- `_rotvec`: rotation vectors and interpolation, `quat_from_rotvec`, `quat_to_rotvec` and
  `slerp`;
- `_euler`: the twelve Euler/Cardan sequences, `euler_to_quat`, `euler_to_dcm`,
  `quat_to_euler`, `dcm_to_euler`, `gimbal_lock_distance` (`GIMBAL_LOCK_EPS`),
  `euler_rates_to_omega` and `omega_to_euler_rates`;
- `_kinematics`: the kinematic equations, `quat_derivative`, `dcm_derivative`,
  `omega_from_dcm`, `poisson`, and `skew` and `vee`;
- `_common`: the batch broadcast, the dot product and the norm, `atan2` and `hypot` safe at
  zero, shared by the modules above.
"""

from ._euler import (
    GIMBAL_LOCK_EPS as GIMBAL_LOCK_EPS,
    dcm_to_euler as dcm_to_euler,
    euler_rates_to_omega as euler_rates_to_omega,
    euler_to_dcm as euler_to_dcm,
    euler_to_quat as euler_to_quat,
    gimbal_lock_distance as gimbal_lock_distance,
    omega_to_euler_rates as omega_to_euler_rates,
    quat_to_euler as quat_to_euler,
)
from ._kinematics import (
    dcm_derivative as dcm_derivative,
    omega_from_dcm as omega_from_dcm,
    poisson as poisson,
    quat_derivative as quat_derivative,
    skew as skew,
    vee as vee,
)
from ._quaternion import (
    dcm_to_quat as dcm_to_quat,
    quat_conjugate as quat_conjugate,
    quat_multiply as quat_multiply,
    quat_normalize as quat_normalize,
    quat_rotate as quat_rotate,
    quat_to_dcm as quat_to_dcm,
)
from ._rotvec import (
    quat_from_rotvec as quat_from_rotvec,
    quat_to_rotvec as quat_to_rotvec,
    slerp as slerp,
)

__all__ = [
    "GIMBAL_LOCK_EPS",
    "dcm_derivative",
    "dcm_to_euler",
    "dcm_to_quat",
    "euler_rates_to_omega",
    "euler_to_dcm",
    "euler_to_quat",
    "gimbal_lock_distance",
    "omega_from_dcm",
    "omega_to_euler_rates",
    "poisson",
    "quat_conjugate",
    "quat_derivative",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_to_dcm",
    "quat_to_euler",
    "quat_to_rotvec",
    "skew",
    "slerp",
    "vee",
]
