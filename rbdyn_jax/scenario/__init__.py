"""Scenarios: a model, distributions of its parameters and initial conditions, output times,
solver settings and the per-trajectory summaries to keep, validated from TOML.

A scenario is written in TOML (`Scenario.from_toml`, shipped ones in `rbdyn_jax/scenarios/`)
or given as the same nested dict (`Scenario.from_dict`), and validated: an unknown key or a
bad value raises a `ScenarioError` naming the key (`model.inertia.principal`) and what was
expected. `Scenario.sample` draws one trajectory's values and `Scenario.build` turns them
into a model and an initial state; `rbdyn_jax.sweep` runs many of them.

The torques and frames a scenario may name are the registries `TORQUES` and `FRAMES`
(kind → `Kind`: class, accepted keys, builder); `DISTRIBUTIONS` and `SUMMARIES` list the
distributions and summaries.

The modules, one idea each:

- `_distributions`: the distributions of a quantity (`AbstractDistribution`, `Fixed`,
  `Normal`, …, `DispersedInertia`) and `DISTRIBUTIONS`, those a `dist` may name;
- `_validate`: `ScenarioError` and the validation of a table's values, each error naming
  the key path;
- `_kinds`: the registries of torque and frame kinds, `TORQUES` and `FRAMES` (`Kind`,
  `Param`);
- `_summaries`: the per-trajectory summaries, `SUMMARIES` (`Summary`);
- `_scenario`: `Scenario` itself (loading, validating, sampling, building) and the solver
  methods it may name, `SOLVERS` and `FIXED_STEP`.

The shipped scenario files are listed by `rbdyn_jax/_catalogue.py` (`SCENARIO_DIR`,
`list_scenarios`), which reads them without JAX.
"""

from .._catalogue import SCENARIO_DIR as SCENARIO_DIR, list_scenarios as list_scenarios
from ._distributions import (
    DISTRIBUTIONS as DISTRIBUTIONS,
    AbstractDistribution as AbstractDistribution,
    DispersedInertia as DispersedInertia,
    EulerAttitude as EulerAttitude,
    Fixed as Fixed,
    LogNormal as LogNormal,
    Normal as Normal,
    Uniform as Uniform,
    UniformSO3 as UniformSO3,
)
from ._kinds import FRAMES as FRAMES, TORQUES as TORQUES, Kind as Kind, Param as Param
from ._scenario import FIXED_STEP as FIXED_STEP, SOLVERS as SOLVERS, Scenario as Scenario
from ._summaries import SUMMARIES as SUMMARIES, Summary as Summary
from ._validate import ScenarioError as ScenarioError

__all__ = [
    "DISTRIBUTIONS",
    "FIXED_STEP",
    "FRAMES",
    "SCENARIO_DIR",
    "SOLVERS",
    "SUMMARIES",
    "TORQUES",
    "AbstractDistribution",
    "DispersedInertia",
    "EulerAttitude",
    "Fixed",
    "Kind",
    "LogNormal",
    "Normal",
    "Param",
    "Scenario",
    "Summary",
    "ScenarioError",
    "Uniform",
    "UniformSO3",
    "list_scenarios",
]
