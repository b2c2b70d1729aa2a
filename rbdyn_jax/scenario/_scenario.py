"""`Scenario`: a validated sweep scenario, from TOML or a dict, and the solver methods it may
name (`SOLVERS`, `FIXED_STEP`); it draws one trajectory's values and builds its model and
initial state."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import tomllib
from collections.abc import Mapping
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._catalogue import SCENARIO_DIR, list_scenarios
from ..integrate import (
    MAX_STEPS,
    RESULTS,
    SPLITTING_ORDERS,
    LiePoissonSplitting,
    Trajectory,
    default_tolerance,
    fixed_steps,
    min_rtol,
)
from ..models import RelativeRigidBody, RigidBody
from ..state import State
from ._distributions import AbstractDistribution, UniformSO3, _as_dtype, _path_key
from ._kinds import FRAMES, TORQUES, _kind, _kinded
from ._summaries import SUMMARIES
from ._validate import (
    ScenarioError,
    _attitude,
    _fail,
    _inertia_spec,
    _number,
    _quantity,
    _table,
    _trajectories,
)

SOLVERS = ("Tsit5", "Dopri5", "Dopri8", "LiePoissonSplitting")
# The fixed-step, structure-preserving methods (`[solver] dt`, `order`); the others are
# diffrax's adaptive ones (`[solver] rtol`, `atol`).
FIXED_STEP = ("LiePoissonSplitting",)
_DTYPES = ("float64", "float32")


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A validated sweep scenario (build with `from_toml`, `from_dict` or `load`).

    `dists` is the pytree of distributions (key path → distribution module); the structure
    (model kind, torque and frame kinds, `static` settings by key path, summaries) is
    static. `rtol` and `atol` are an adaptive method's tolerances, `dt` and `order` a
    fixed-step method's step and order (`FIXED_STEP`; `None` where they do not apply).
    `dtype` (`[solver] dtype`, "float64" or "float32") is the dtype of every array
    it makes: its distributions, output times, draws and built models; `trajectories`
    (`[outputs] trajectories`: "all", "none" or K) whose states a sweep stores. The file
    format is documented in docs/scenarios.md (the shipped examples are
    `rbdyn_jax/scenarios/*.toml`); `TORQUES`, `FRAMES`, `DISTRIBUTIONS` and `SUMMARIES` list
    the accepted kinds.

    A scenario is a pytree: its leaves are those of `dists` (arrays, traced inside a
    compiled program), and everything else is its static structure, equal between two
    scenarios of the same source (`Structure`). A compiled program takes it as an argument,
    compiled once per source.
    """

    name: str
    description: str
    kind: str
    torques: tuple[str, ...]
    frame: str
    static: dict[str, Any]
    dists: dict[str, AbstractDistribution]
    t0: float
    t1: float
    n_times: int
    solver: str
    rtol: float | None
    atol: float | None
    max_steps: int
    dtype: str
    summaries: tuple[str, ...]
    trajectories: str | int
    source: dict
    dt: float | None = None
    order: int | None = None

    TOP = {"name", "description", "model", "initial", "time", "solver", "outputs"}

    @classmethod
    def from_toml(cls, path: str | pathlib.Path) -> Scenario:
        path = pathlib.Path(path)
        try:
            d = tomllib.loads(path.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ScenarioError(f"{path}: not valid TOML: {e}") from None
        except OSError as e:  # a directory, unreadable, …
            raise ScenarioError(f"{path}: cannot read it as a scenario: {e.strerror}") from None
        return cls.from_dict(d, default_name=path.stem)

    @classmethod
    def load(cls, name_or_path: str | pathlib.Path) -> Scenario:
        """A shipped scenario by name (`list_scenarios()`), or a TOML file."""
        p = pathlib.Path(name_or_path)
        if not p.exists() and (SCENARIO_DIR / f"{name_or_path}.toml").exists():
            p = SCENARIO_DIR / f"{name_or_path}.toml"
        if not p.exists():
            raise ScenarioError(
                f"no scenario file {str(name_or_path)!r} and no shipped "
                f"scenario of that name (shipped: {list_scenarios()})"
            )
        return cls.from_toml(p)

    @classmethod
    def from_dict(cls, d: Mapping, *, default_name: str = "scenario") -> Scenario:
        d = _table(d, "", cls.TOP, {"model", "initial", "time"})
        name = d.get("name", default_name)
        if not isinstance(name, str) or not name:
            raise _fail("name", "a non-empty string", name)
        description = d.get("description", "")
        if not isinstance(description, str):
            raise _fail("description", "a string", description)

        m = _table(
            d["model"], "model", {"kind", "inertia", "torques", "frame"}, {"kind", "inertia"}
        )
        kind = m["kind"]
        if kind not in ("rigid_body", "relative_rigid_body"):
            raise _fail("model.kind", '"rigid_body" or "relative_rigid_body"', kind)
        dists: dict[str, AbstractDistribution] = {
            "model.inertia": _inertia_spec(m["inertia"], "model.inertia")
        }
        static: dict[str, Any] = {}

        def add(prefix, kind_dists, kind_static):  # a kind's keys → key paths
            dists.update({f"{prefix}.{k}": v for k, v in kind_dists.items()})
            static.update({f"{prefix}.{k}": v for k, v in kind_static.items()})

        torques = m.get("torques", [])
        if not isinstance(torques, list):
            raise _fail("model.torques", "an array of tables ([[model.torques]])", torques)
        kinds = []
        for i, tq in enumerate(torques):
            tkind, tdists, tstatic = _kinded(tq, f"model.torques[{i}]", TORQUES)
            kinds.append(tkind)
            add(f"model.torques[{i}]", tdists, tstatic)
        frame = "inertial"
        if "frame" in m:
            if kind != "relative_rigid_body":
                raise _fail(
                    "model.frame",
                    'no frame for kind = "rigid_body" (use "relative_rigid_body")',
                    m["frame"],
                )
            frame, fdists, fstatic = _kinded(m["frame"], "model.frame", FRAMES)
            add("model.frame", fdists, fstatic)
        for tkind in kinds:
            if TORQUES[tkind].relative_only and kind != "relative_rigid_body":
                raise _fail(
                    "model.torques", f'{tkind} only with kind = "relative_rigid_body"', tkind
                )

        ini = _table(d["initial"], "initial", {"omega", "attitude"}, {"omega"})
        dists["initial.omega"] = _quantity(ini["omega"], "initial.omega", (3,))
        dists["initial.attitude"] = _attitude(
            ini.get("attitude", [1.0, 0.0, 0.0, 0.0]), "initial.attitude"
        )

        tt = _table(d["time"], "time", {"t0", "t1", "n"}, {"t1", "n"})
        t0 = float(_number(tt.get("t0", 0.0), "time.t0"))
        t1 = float(_number(tt["t1"], "time.t1"))
        if not t1 > t0:
            raise _fail("time.t1", f"a time after t0 = {t0}", tt["t1"])
        if not np.isfinite(t1 - t0):
            raise _fail("time.t1", f"a time a finite span after t0 = {t0}", tt["t1"])
        n_times = int(_number(tt["n"], "time.n", integer=True))
        if n_times < 2:
            raise _fail("time.n", "an integer ≥ 2 (output times, linspace(t0, t1, n))", tt["n"])

        s = _table(
            d.get("solver", {}),
            "solver",
            {"method", "rtol", "atol", "max_steps", "dtype", "dt", "order"},
        )
        method = s.get("method", "Tsit5")
        if method not in SOLVERS:
            raise _fail("solver.method", f"one of {list(SOLVERS)}", method)
        dtype = s.get("dtype", "float64")
        if not isinstance(dtype, str) or dtype not in _DTYPES:
            raise _fail("solver.dtype", '"float64" or "float32"', dtype)
        rtol = atol = dt = order = None
        if method in FIXED_STEP:
            for key in ("rtol", "atol"):
                if key in s:
                    raise _fail(
                        f"solver.{key}",
                        f'no tolerance with method = "{method}" '
                        "(it takes fixed steps: give solver.dt)",
                        s[key],
                    )
            if "dt" not in s:
                raise _fail(
                    "solver.dt",
                    f'the fixed step of method = "{method}" (a number > 0, in the unit of time)',
                )
            dt = float(_number(s["dt"], "solver.dt", positive=True))
            if dt > t1 - t0:
                raise _fail("solver.dt", f"a step no longer than t1 − t0 = {t1 - t0:g}", dt)
            order = int(_number(s.get("order", 6), "solver.order", integer=True))
            if order not in SPLITTING_ORDERS:
                raise _fail("solver.order", " or ".join(map(str, SPLITTING_ORDERS)), order)
            steps = fixed_steps(t1 - t0, dt)
            # One more by default: the rounding of the step's times may leave a short last one.
            max_steps = int(
                _number(
                    s.get("max_steps", steps + 1), "solver.max_steps", integer=True, positive=True
                )
            )
            if max_steps < steps:
                raise _fail(
                    "solver.max_steps",
                    f"at least the {steps} steps of dt over [t0, t1] (or leave it out)",
                    max_steps,
                )
        else:
            for key in ("dt", "order"):
                if key in s:
                    raise _fail(
                        f"solver.{key}",
                        f"only with method = one of {list(FIXED_STEP)}"
                        " (an adaptive method chooses its steps)",
                        s[key],
                    )
            default_tol = default_tolerance(dtype)  # 1e-8, or 1e-6 in float32
            rtol = float(_number(s.get("rtol", default_tol), "solver.rtol", positive=True))
            if rtol < min_rtol(dtype):  # the step-size control would compare with rounding
                raise _fail(
                    "solver.rtol",
                    f"a number ≥ {min_rtol(dtype):.2g} with dtype = "
                    f'"{dtype}" (8 machine epsilons of {dtype}: a finer tolerance is '
                    "below its rounding)",
                    rtol,
                )
            atol = float(_number(s.get("atol", default_tol), "solver.atol", positive=True))
            max_steps = int(
                _number(s.get("max_steps", 16384), "solver.max_steps", integer=True, positive=True)
            )
        if max_steps > MAX_STEPS:  # a step counter is int32 in float32
            raise _fail("solver.max_steps", f"an integer ≤ {MAX_STEPS}", max_steps)

        o = _table(d.get("outputs", {}), "outputs", {"summaries", "trajectories"})
        trajectories = _trajectories(o.get("trajectories", "all"), "outputs.trajectories")
        summaries = o.get("summaries", ["max_nutation", "min_abs_omega", "max_abs_omega"])
        if not isinstance(summaries, list) or not all(isinstance(x, str) for x in summaries):
            raise _fail("outputs.summaries", f"a list of names from {sorted(SUMMARIES)}", summaries)
        for x in summaries:
            if x not in SUMMARIES:
                raise _fail("outputs.summaries", f"names from {sorted(SUMMARIES)}", x)
        if len(set(summaries)) != len(summaries):
            raise _fail("outputs.summaries", "no repeated names", summaries)

        if dtype != "float64":
            dists = {
                p: UniformSO3(jnp.float32) if isinstance(v, UniformSO3) else _as_dtype(v, dtype)
                for p, v in dists.items()
            }
        sc = cls(
            name=name,
            description=description,
            kind=kind,
            torques=tuple(kinds),
            frame=frame,
            static=static,
            dists=dists,
            t0=t0,
            t1=t1,
            n_times=n_times,
            solver=method,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
            dtype=dtype,
            summaries=tuple(summaries),
            trajectories=trajectories,
            source=json.loads(json.dumps(dict(d))),
            dt=dt,
            order=order,
        )
        sc._check_solver()
        sc._check_summaries()
        return sc

    def with_settings(
        self, *, dtype: str | None = None, trajectories: str | int | None = None
    ) -> Scenario:
        """This scenario with `[solver] dtype` and/or `[outputs] trajectories` set to the
        values given (`None` keeps the scenario's): its source with those keys replaced,
        validated again, so that a bad value, or a `solver.rtol` finer than the new dtype
        resolves, is a `ScenarioError` naming the key. The source, which a sweep store
        keeps, then holds the values the scenario runs with. Returns `self` when nothing
        changes."""
        source = json.loads(json.dumps(self.source))
        changed = False
        for table, key, value in (
            ("solver", "dtype", dtype),
            ("outputs", "trajectories", trajectories),
        ):
            # By type too: `True == 1`, and a bool must reach the validation (which refuses it).
            if value is not None and (
                value != getattr(self, key) or type(value) is not type(getattr(self, key))
            ):
                source.setdefault(table, {})[key] = value
                changed = True
        return Scenario.from_dict(source, default_name=self.name) if changed else self

    # -- solver settings -----------------------------------------------------------------

    @property
    def fixed_step(self) -> bool:
        """Whether the `[solver] method` takes fixed steps `dt` (`LiePoissonSplitting`)."""
        return self.solver in FIXED_STEP

    @property
    def diffrax_solver(self) -> diffrax.AbstractSolver:
        """A fresh instance of the `[solver] method` (`diffrax.Tsit5()`, …,
        `LiePoissonSplitting(order)`)."""
        if self.solver == "LiePoissonSplitting":
            return LiePoissonSplitting(self.order)
        return getattr(diffrax, self.solver)()

    @property
    def stepsize_controller(self) -> diffrax.AbstractStepSizeController:
        """The step-size controller of the `[solver]` settings: a `diffrax.PIDController`
        of the tolerances for an adaptive method, `diffrax.ConstantStepSize()` (steps of
        `dt`, the solve's `dt0`) for a fixed-step one."""
        if self.fixed_step:
            return diffrax.ConstantStepSize()
        return diffrax.PIDController(rtol=self.rtol, atol=self.atol)

    # -- building one trajectory ----------------------------------------------------------

    @property
    def ts(self) -> np.ndarray:
        """The output times, `linspace(t0, t1, n)` in the scenario's dtype."""
        return np.linspace(self.t0, self.t1, self.n_times, dtype=self.dtype)

    def nominal(self) -> dict[str, jax.Array]:
        """The centre of every distribution (its mean, median or fixed value)."""
        return {path: dist.centre() for path, dist in self.dists.items()}

    def build(self, values: Mapping[str, jax.Array]) -> tuple[eqx.Module, State]:
        """The model and initial state for one set of drawn `values` (key path → value), in
        the scenario's dtype. Every torque and frame kind is looked up in `TORQUES` /
        `FRAMES`: an unregistered one raises a `ScenarioError`."""
        torque = None
        for i, kind in enumerate(self.torques):
            tq = self._make(TORQUES, kind, f"model.torques[{i}]", values)
            torque = tq if torque is None else torque + tq
        J = values["model.inertia"]
        y0 = State(omega=values["initial.omega"], quat=values["initial.attitude"])
        if self.kind == "rigid_body":
            model = RigidBody(J, torque)
        else:
            frame = self._make(FRAMES, self.frame, "model.frame", values)
            model = RelativeRigidBody(J, frame, torque)
        if self.dtype == "float64":
            return model, y0
        # The defaults the classes fill in (a frame's zero coefficients, …) in the dtype too.
        return _as_dtype((model, y0), self.dtype)

    def _make(self, registry, kind, path, values) -> eqx.Module:
        """The object of `kind` at `path` from its drawn `values` and static settings."""
        spec = _kind(registry, kind, f"{path}.kind")
        parts = {}
        for name in spec.params:
            key = f"{path}.{name}"
            if key in values:
                parts[name] = values[key]
            elif key in self.static:
                parts[name] = self.static[key]
        return spec.make(parts)

    def sample(self, dists: Mapping[str, AbstractDistribution], key, index) -> dict[str, jax.Array]:
        """The drawn values of trajectory `index` (traceable)."""
        k = jax.random.fold_in(key, index)
        return {path: dist.sample(_path_key(k, path)) for path, dist in dists.items()}

    def _check_solver(self):
        """A fixed-step method that cannot integrate the model (a relative model, a torque
        that depends on the rates) is refused now, naming `solver.method`."""
        if not self.fixed_step:
            return
        model, _ = jax.eval_shape(lambda: self.build(self.nominal()))
        try:
            self.diffrax_solver.check_model(model)
        except ValueError as e:
            raise ScenarioError(f"`solver.method`: {e}") from None

    def _check_summaries(self):
        def nominal_run():
            model, y0 = self.build(self.nominal())
            ys = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), y0)
            return model, Trajectory(
                ts=jnp.asarray(self.ts[:2]), ys=ys, stats={}, result=RESULTS.successful
            )

        # Shapes only (nothing computed or compiled): what the summaries are traced with.
        model, traj = jax.eval_shape(nominal_run)
        for name in self.summaries:
            try:
                jax.eval_shape(lambda m, tr, f=SUMMARIES[name].fn: f(m, tr), model, traj)
            except (ValueError, AttributeError) as e:
                raise ScenarioError(
                    f"`outputs.summaries`: {name!r} is not defined for this model: {e}"
                ) from None


class Structure:
    """The static part of a `Scenario`'s pytree (all but its distributions' leaves): equal
    and hashed by the JSON text of the scenario's source with the settings `with_settings`
    changes written out (a source that leaves `dtype` or `trajectories` to its default and
    one that names the default are one structure); the text is also its `repr` (an exact
    description, which the cache of traced programs keys a stored program by)."""

    __slots__ = ("scenario", "text")

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        source = json.loads(json.dumps(scenario.source))
        source.setdefault("solver", {})["dtype"] = scenario.dtype
        source.setdefault("outputs", {})["trajectories"] = scenario.trajectories
        self.text = json.dumps(source, sort_keys=True)

    def __eq__(self, other) -> bool:
        return isinstance(other, Structure) and self.text == other.text

    def __hash__(self) -> int:
        return hash(self.text)

    def __repr__(self) -> str:
        return f"Structure({self.text})"


jax.tree_util.register_pytree_with_keys(
    Scenario,
    lambda sc: (((jax.tree_util.GetAttrKey("dists"), sc.dists),), Structure(sc)),
    lambda structure, children: dataclasses.replace(structure.scenario, dists=children[0]),
    flatten_func=lambda sc: ((sc.dists,), Structure(sc)),
)
