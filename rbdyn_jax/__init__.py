"""rbdyn_jax: differentiable rotational dynamics of rigid bodies in JAX.

Conventions (PHYSICS.md §1): quaternions are Hamilton, scalar first `[w, x, y, z]`;
`R(q)` maps body components to parent components; Euler sequences follow
`scipy.spatial.transform.Rotation` (upper case intrinsic, lower case extrinsic).
The library never switches on float64: call `jax.config.update("jax_enable_x64", True)`.
"""

from . import dynamics as dynamics, inertia as inertia, rotation as rotation

__version__ = "0.1.0"
