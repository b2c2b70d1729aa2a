"""Parameter identification: fit inertia, torque parameters and initial states to observed
trajectories through the solver (docs/physics.md#inertia, docs/physics.md#absolute-motion,
docs/physics.md#restoring-moment).

- `Observations(ts, omega=None, quat=None, sigma_omega=None, sigma_quat=None, mask=None)`:
  K trajectories of n samples (padded and masked where their lengths differ), checked once
  when built; `Observations.from_file(path)` reads them from an NPZ, CSV or netCDF file or
  a sweep store.
- `residuals(model, y0s, data, ...)`: the whitened residual vector — ω residuals divided by
  `sigma_omega`, attitude residuals as the rotation vector of `q_obs* ⊗ q_sim` (its norm is the
  geodesic angle, sign-invariant, finite gradient at zero) divided by `sigma_quat` — over all
  trajectories at once (`jax.vmap`, no Python loop over trajectories). `loss` is ½ Σ r².
- `fit(model, data, *, params=("inertia", "initial_conditions"), ...) -> FitResult`: the
  inertia free through the log-Cholesky parameters of J'
  (docs/physics.md#log-cholesky-parametrisation, every iterate is physical), the torque's
  array leaves, and the initial state of every trajectory (ω0 and a rotation-vector
  correction of q0). The `optimizer`, an `AbstractOptimizer`, is `LevenbergMarquardt()` on
  the residual vector (default) or `Optax(tx)`, any optax transformation on the loss; either
  runs inside **one** compiled program with the Gauss–Newton covariance `(JᵀJ)⁻¹` at the
  optimum. Step-size control is a diffrax controller passed through to `simulate`
  (`stepsize_controller=`; `rtol=`/`atol=` are shorthand for a `PIDController`).

Identifiability: with no torque, Euler's equations `J ω' = J ω × ω` are unchanged by `J → cJ`,
so data fix J only up to scale. `fit` detects the near-null direction of `JᵀJ` along the
scaling of J and reports it (`FitResult.scale_identified = False`, inertia standard errors
`inf`); pass `scale=`, an `AbstractScale`: `TraceScale(value)` (tr J = value) or
`MomentScale(axis, value)` (the moment of inertia about `axis`), or a known torque in the
model, to fix the scale.

The modules, one idea each:

- `_observations`: `Observations`, the observed records and their checks;
- `_observation_files`: the NPZ, CSV and xarray files `Observations.from_file` reads;
- `_residuals`: `residuals` and `loss` of a model against `Observations`;
- `_scale`: the scale gauges `AbstractScale`, `TraceScale` and `MomentScale`, and the
  inertia rescaled onto one;
- `_optimizers`: `AbstractOptimizer`, `LevenbergMarquardt` and `Optax`, the loops the fit
  runs on its objective;
- `_problem`: the fit's compiled program, from the starting point through the optimiser
  to the covariance at the optimum;
- `_fit`: `fit`, which checks its arguments and runs that program, and its `FitResult`.
"""

from ._fit import FitResult as FitResult, fit as fit
from ._observations import Observations as Observations
from ._optimizers import (
    AbstractOptimizer as AbstractOptimizer,
    LevenbergMarquardt as LevenbergMarquardt,
    Optax as Optax,
)
from ._residuals import loss as loss, residuals as residuals
from ._scale import (
    AbstractScale as AbstractScale,
    MomentScale as MomentScale,
    TraceScale as TraceScale,
)

__all__ = [
    "AbstractOptimizer",
    "AbstractScale",
    "FitResult",
    "LevenbergMarquardt",
    "MomentScale",
    "Observations",
    "Optax",
    "TraceScale",
    "fit",
    "loss",
    "residuals",
]
