"""Closed-form and quadrature reference solutions, used to check the simulator.

Nothing here integrates an ODE: every function is a closed form, a special function, or a
fixed quadrature, so it is independent of the diffrax machinery it is meant to check.

- Torque-free axisymmetric body, angular velocity and attitude in closed form
  (docs/physics.md#torque-free-motion): `torque_free_symmetric`.
- Torque-free triaxial body, Jacobi elliptic functions (docs/physics.md#torque-free-motion;
  Landau & Lifshitz, *Mechanics* §37) on both sides of the separatrix and on it:
  `torque_free_elliptic`, `torque_free_elliptic_period`, with the special functions
  `ellipj`, `ellipk`, `ellipkinc` implemented in JAX (descending Landen transformation and
  Carlson's `R_F`).
- Lagrange top under a non-stationary restoring moment `k = ε K(τ) sin ψ`
  (Zinkevich & Kozachenko (2008); docs/physics.md#restoring-moment): first approximation
  `lagrange_top_first_approximation` and a second approximation
  `lagrange_top_second_approximation`.
- Integrable gravity-gradient case `A = B = m C` (Shinibaev et al. (2013);
  docs/physics.md#the-integrable-case): the nutation half period by quadrature,
  `gg_nutation_half_period`, its quartic `gg_nutation_quartic`, and the first integrals
  `gg_integrable_case_integrals`.

The JAX functions are pure, jit-able and accept leading `*batch` axes; the nutation
quadrature is NumPy/SciPy (a reference evaluated once per initial condition).

The modules, one idea each:

- `_elliptic`: the elliptic functions `ellipj`, `ellipk`, `ellipkinc` (descending Landen
  transformation, Carlson's `R_F`), and their forms in the complementary parameter;
- `_torque_free`: torque-free motion, `torque_free_symmetric`, `torque_free_elliptic` and
  `torque_free_elliptic_period`;
- `_lagrange_top`: the Lagrange top under a restoring moment,
  `lagrange_top_first_approximation` and `lagrange_top_second_approximation`;
- `_gravity_gradient`: the integrable gravity-gradient case, `gg_integrable_case_integrals`,
  `gg_nutation_quartic` and `gg_nutation_half_period`;
- `_helpers`: the inputs' conversion, broadcasting and checks, and arithmetic safe in the
  discarded branches of a `where`, shared by the modules above.
"""

from ._elliptic import ellipj as ellipj, ellipk as ellipk, ellipkinc as ellipkinc
from ._gravity_gradient import (
    gg_integrable_case_integrals as gg_integrable_case_integrals,
    gg_nutation_half_period as gg_nutation_half_period,
    gg_nutation_quartic as gg_nutation_quartic,
)
from ._lagrange_top import (
    lagrange_top_first_approximation as lagrange_top_first_approximation,
    lagrange_top_second_approximation as lagrange_top_second_approximation,
)
from ._torque_free import (
    torque_free_elliptic as torque_free_elliptic,
    torque_free_elliptic_period as torque_free_elliptic_period,
    torque_free_symmetric as torque_free_symmetric,
)

__all__ = [
    "ellipj",
    "ellipk",
    "ellipkinc",
    "gg_integrable_case_integrals",
    "gg_nutation_half_period",
    "gg_nutation_quartic",
    "lagrange_top_first_approximation",
    "lagrange_top_second_approximation",
    "torque_free_elliptic",
    "torque_free_elliptic_period",
    "torque_free_symmetric",
]
