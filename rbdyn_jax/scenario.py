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
"""

from __future__ import annotations

import abc
import dataclasses
import json
import math
import pathlib
import tomllib
import zlib
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import inertia as _inertia, invariants, rotation
from ._catalogue import SCENARIO_DIR as SCENARIO_DIR, list_scenarios as list_scenarios
from ._vector import parse_seq
from .frames import CircularOrbit, ConstantRate, EulerAngleFrame, HarmonicAngles, Inertial
from .integrate import (
    RESULTS,
    SPLITTING_ORDERS,
    LiePoissonSplitting,
    Trajectory,
    default_tolerance,
    fixed_steps,
    min_rtol,
)
from .models import RelativeRigidBody, RigidBody
from .state import State
from .torques import (
    BalancingTransport,
    BodyTorque,
    GravityGradient,
    InertialTorque,
    PolynomialSinPsi,
    RestoringMoment,
    UniformGravity,
)


class ScenarioError(ValueError):
    """A scenario file or dict that does not validate; the message names the key."""


# ----------------------------------------------------------------------------------------
# Distributions: eqx.Modules whose leaves are arrays, so they enter the compiled sweep as
# runtime arguments.
# ----------------------------------------------------------------------------------------


class AbstractDistribution(eqx.Module):
    """The distribution of one quantity: `sample(key)` gives one draw, `centre()` its
    nominal value (the scenario's nominal model, and the stand-in for a non-finite draw)."""

    @abc.abstractmethod
    def sample(self, key) -> jax.Array:
        ...

    @abc.abstractmethod
    def centre(self) -> jax.Array:
        ...


class Fixed(AbstractDistribution):
    """Always `value`."""

    value: jax.Array

    def sample(self, key):
        return self.value

    def centre(self):
        return self.value


class Normal(AbstractDistribution):
    """Independent normal components, `mean + std · N(0, 1)`; centred on `mean`."""

    mean: jax.Array
    std: jax.Array

    def sample(self, key):
        return self.mean + self.std * jax.random.normal(key, self.mean.shape, self.mean.dtype)

    def centre(self):
        return self.mean


class Uniform(AbstractDistribution):
    """Independent uniform components on `[low, high)`; centred on the mid-point."""

    low: jax.Array
    high: jax.Array

    def sample(self, key):
        u = jax.random.uniform(key, self.low.shape, self.low.dtype)
        return self.low + (self.high - self.low) * u

    def centre(self):
        return 0.5 * (self.low + self.high)


class LogNormal(AbstractDistribution):
    """`median · exp(sigma · N(0, 1))`, componentwise (positive quantities); centred on
    `median`."""

    median: jax.Array
    sigma: jax.Array

    def sample(self, key):
        z = jax.random.normal(key, self.median.shape, self.median.dtype)
        return self.median * jnp.exp(self.sigma * z)

    def centre(self):
        return self.median


class UniformSO3(AbstractDistribution):
    """A uniformly distributed attitude: a normalised 4-D Gaussian (Haar measure on SO(3)),
    sign fixed to w ≥ 0. It has no centre: `centre()` is the identity."""

    dtype: Any = eqx.field(static=True, default=jnp.float64)

    def sample(self, key):
        q = jax.random.normal(key, (4,), self.dtype)
        q = q / jnp.linalg.norm(q)
        return jnp.where(q[0] < 0, -q, q)

    def centre(self):
        # A NumPy array of the dtype, made a JAX array of the default float where float64
        # is off: no warning for a dtype JAX does not have.
        return jnp.asarray(np.array([1.0, 0.0, 0.0, 0.0], np.dtype(self.dtype)))


class EulerAttitude(AbstractDistribution):
    """Attitude from Euler angles drawn from `angles` (a distribution) in sequence `seq`;
    centred on the attitude of the centre angles."""

    angles: AbstractDistribution
    seq: str = eqx.field(static=True)

    def sample(self, key):
        return rotation.euler_to_quat(self.angles.sample(key), self.seq)

    def centre(self):
        return rotation.euler_to_quat(self.angles.centre(), self.seq)


class DispersedInertia(AbstractDistribution):
    """A physical inertia around `nominal`: the log-Cholesky coordinates θ of its planar
    tensor J' = L Lᵀ (`inertia.to_log_cholesky`) are perturbed, the log-diagonal by
    `sigma · N(0, 1)` and each off-diagonal `L_ij` by `sigma · sqrt(L_ii L_jj) · N(0, 1)`,
    a relative spread of about `sigma` in every moment and product of inertia. Every sample
    is physical (triangle inequalities hold) by construction
    (docs/physics.md#log-cholesky-parametrisation). Centred on `nominal`."""

    nominal: jax.Array
    sigma: jax.Array

    def sample(self, key):
        theta = _inertia.to_log_cholesky(self.nominal)
        d = jnp.exp(theta[:3])
        scale = jnp.stack([1.0, 1.0, 1.0, jnp.sqrt(d[1] * d[0]), jnp.sqrt(d[2] * d[0]),
                           jnp.sqrt(d[2] * d[1])]).astype(theta.dtype)
        z = jax.random.normal(key, (6,), theta.dtype)
        return _inertia.from_log_cholesky(theta + self.sigma * scale * z)

    def centre(self):
        return self.nominal


# The distributions a quantity's `dist` may name; their fields are the table's keys.
DISTRIBUTIONS: dict[str, type[AbstractDistribution]] = {
    "fixed": Fixed,
    "normal": Normal,
    "uniform": Uniform,
    "lognormal": LogNormal,
}


def _path_key(key, path: str):
    return jax.random.fold_in(key, zlib.crc32(path.encode()) & 0x7FFFFFFF)


def _as_dtype(tree, dtype):
    """`tree` with every floating array in `dtype`. JAX computes in float32 only where every
    input is float32 (a float64 array, with float64 enabled, promotes the whole solve), so
    a float32 scenario's distributions, models and states are cast to it explicitly;
    concrete arrays through NumPy (no JAX program for the cast)."""
    dtype = np.dtype(dtype)

    def cast(x):
        if not eqx.is_array(x) or not jnp.issubdtype(x.dtype, jnp.floating) or x.dtype == dtype:
            return x
        if isinstance(x, jax.core.Tracer):
            return x.astype(dtype)
        return jnp.asarray(np.asarray(x).astype(dtype))

    return jax.tree_util.tree_map(cast, tree)


# ----------------------------------------------------------------------------------------
# Validation helpers: every error names the dotted key path and what was expected.
# ----------------------------------------------------------------------------------------


def _fail(path: str, expected: str, got: Any = dataclasses.MISSING) -> ScenarioError:
    tail = "" if got is dataclasses.MISSING else f", got {got!r}"
    return ScenarioError(f"`{path}`: expected {expected}{tail}")


def _table(d: Any, path: str, allowed: set[str], required: set[str] = frozenset()) -> dict:
    if not isinstance(d, Mapping):
        raise _fail(path, "a table", d)
    unknown = sorted(set(d) - allowed)
    if unknown:
        where = f"{path}.{unknown[0]}" if path else unknown[0]
        raise ScenarioError(f"`{where}`: unknown key; expected one of {sorted(allowed)}")
    for key in sorted(required):
        if key not in d:
            raise _fail(f"{path}.{key}" if path else key, "this key to be present (missing)")
    return dict(d)


def _number(x, path, *, positive=False, nonneg=False, integer=False) -> float | int:
    ok_type = isinstance(x, int) if integer else isinstance(x, int | float)
    if isinstance(x, bool) or not ok_type:
        raise _fail(path, "an integer" if integer else "a number", x)
    if not math.isfinite(x):
        raise _fail(path, "a finite number", x)
    if positive and not x > 0:
        raise _fail(path, "a positive number", x)
    if nonneg and not x >= 0:
        raise _fail(path, "a number ≥ 0", x)
    return x


def _array(x, path, shape: tuple[int, ...], *, positive=False, nonneg=False) -> np.ndarray:
    """A number or nested list of numbers of `shape` (a scalar broadcasts to it)."""
    desc = "a number" if shape == () else f"a number or a list of shape {list(shape)}"
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, desc, x) from None
    if isinstance(x, bool) or a.dtype == object or isinstance(x, str):
        raise _fail(path, desc, x)
    if a.shape != shape:
        if a.ndim != 0:
            raise _fail(path, f"{desc} (shape {list(a.shape)} given)", x)
        a = np.broadcast_to(a, shape)
    if not np.all(np.isfinite(a)):
        raise _fail(path, "finite numbers", x)
    if positive and not np.all(a > 0):
        raise _fail(path, "positive numbers", x)
    if nonneg and not np.all(a >= 0):
        raise _fail(path, "numbers ≥ 0", x)
    return np.array(a)


def _quantity(x, path, shape=(), *, positive=False) -> AbstractDistribution:
    """A literal (→ `Fixed`) or a distribution table `{dist = "normal", mean, std}` …"""
    if not isinstance(x, Mapping):
        return Fixed(jnp.asarray(_array(x, path, shape, positive=positive)))
    if "dist" not in x:
        raise _fail(f"{path}.dist", f"one of {sorted(DISTRIBUTIONS)} (missing)")
    kind = x["dist"]
    if kind not in DISTRIBUTIONS:
        raise _fail(f"{path}.dist", f"one of {sorted(DISTRIBUTIONS)}", kind)
    cls = DISTRIBUTIONS[kind]
    fields = {f.name for f in dataclasses.fields(cls)}
    _table(x, path, fields | {"dist"}, fields)
    vals = {}
    for f in sorted(fields):
        nonneg = f in ("std", "sigma")
        pos = f == "median" or (positive and f in ("value", "low", "mean"))
        vals[f] = jnp.asarray(_array(x[f], f"{path}.{f}", shape, positive=pos, nonneg=nonneg))
    if kind == "uniform" and not np.all(np.asarray(vals["high"]) > np.asarray(vals["low"])):
        raise _fail(f"{path}.high", "values greater than `low`", x["high"])
    if positive and kind == "normal":
        raise _fail(f"{path}.dist", "a positive distribution (fixed, uniform or lognormal)",
                    kind)
    return cls(**vals)


def _quat_array(x, path) -> np.ndarray:
    q = _array(x, path, (4,))
    n = np.linalg.norm(q)
    if not abs(n - 1.0) < 1e-6:
        raise _fail(path, "a unit quaternion [w, x, y, z]", x)
    return q / n


def _euler_seq(x, path) -> str:
    try:
        parse_seq(x)
    except (ValueError, TypeError):
        raise _fail(path, "an Euler sequence such as \"ZXZ\" or \"xyz\"", x) from None
    return x


def _attitude(x, path) -> AbstractDistribution:
    if isinstance(x, list):
        return Fixed(jnp.asarray(_quat_array(x, path)))
    t = _table(x, path, {"dist", "quat", "euler", "seq", "degrees"})
    given = [k for k in ("dist", "quat", "euler") if k in t]
    if len(given) != 1:
        raise _fail(path, "exactly one of `dist = \"uniform_so3\"`, `quat` or `euler`",
                    sorted(t))
    if "dist" in t:
        if t["dist"] != "uniform_so3" or set(t) != {"dist"}:
            raise _fail(f"{path}.dist", '"uniform_so3" (alone; use `euler` for others)',
                        t["dist"])
        return UniformSO3()
    if "quat" in t:
        if set(t) != {"quat"}:
            raise _fail(path, "`quat` alone", sorted(t))
        return Fixed(jnp.asarray(_quat_array(t["quat"], f"{path}.quat")))
    seq = _euler_seq(t.get("seq", "ZXZ"), f"{path}.seq")
    degrees = t.get("degrees", False)
    if not isinstance(degrees, bool):
        raise _fail(f"{path}.degrees", "true or false", degrees)
    angles = _quantity(t["euler"], f"{path}.euler", (3,))
    if degrees:  # every leaf (value, mean, std, low, high) is an angle
        angles = jax.tree_util.tree_map(lambda a: a * (np.pi / 180.0), angles)
    return EulerAttitude(angles, seq)


def _trajectories(x, path) -> str | int:
    if isinstance(x, str) and x in ("all", "none"):
        return x
    if isinstance(x, int) and not isinstance(x, bool) and x >= 1:
        return x
    raise _fail(path, '"all", "none" or a positive integer K (the states of trajectories '
                "0, K, 2K, …)", x)


def _inertia_spec(x, path) -> DispersedInertia:
    t = _table(x, path, {"principal", "matrix", "log_cholesky_sigma"})
    if ("principal" in t) == ("matrix" in t):
        raise _fail(path, "exactly one of `principal` or `matrix`", sorted(t))
    if "principal" in t:
        J = np.diag(_array(t["principal"], f"{path}.principal", (3,), positive=True))
        key = f"{path}.principal"
    else:
        J = _array(t["matrix"], f"{path}.matrix", (3, 3))
        key = f"{path}.matrix"
        if not np.allclose(J, J.T, rtol=0, atol=1e-12 * np.abs(J).max()):
            raise _fail(key, "a symmetric 3×3 matrix", t["matrix"])
    if not bool(_inertia.is_physical(jnp.asarray(J))) or not np.all(np.linalg.eigvalsh(J) > 0):
        raise _fail(key, "a physical inertia (positive moments obeying the triangle "
                    "inequalities A + B ≥ C, docs/physics.md#physical-consistency) with no "
                    "zero moment", x.get("principal", x.get("matrix")))
    sigma = _number(t.get("log_cholesky_sigma", 0.0), f"{path}.log_cholesky_sigma", nonneg=True)
    if sigma > 0 and not np.all(np.linalg.eigvalsh(np.asarray(_inertia.planar(J))) > 0):
        raise _fail(f"{path}.log_cholesky_sigma", "0 for a flat body (a zero planar moment, "
                    "A + B = C, has no log-Cholesky coordinates to disperse)", sigma)
    return DispersedInertia(jnp.asarray(J), jnp.asarray(float(sigma)))


# ----------------------------------------------------------------------------------------
# The registry of torque and frame kinds
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Param:
    """One key of a kind's table. `parse(value, path)` validates it and gives a
    distribution (drawn per trajectory), or for a `static` key a plain setting fixed for the
    whole scenario (an Euler sequence: it shapes the compiled program, it is not drawn)."""

    parse: Callable[[Any, str], Any]
    required: bool = False
    static: bool = False


def _quantity_param(shape=(), *, required=False, positive=False) -> Param:
    """A number or array of `shape`, or a distribution of one."""
    return Param(lambda x, path: _quantity(x, path, shape, positive=positive), required)


def _coeffs(x, path) -> AbstractDistribution:
    n = len(x) if isinstance(x, list) else 0
    if n < 1:
        raise _fail(path, "a non-empty list of numbers (K(τ) = Σ c_i τ^i)", x)
    return _quantity(x, path, (n,))


_UNIT_QUAT = Param(lambda x, path: Fixed(jnp.asarray(_quat_array(x, path))))


def _exactly_one(**alternatives: str) -> Callable[[dict, str], None]:
    """A check that the table has exactly one of the keys `alternatives` (key → meaning)."""
    (a, what_a), (b, what_b) = alternatives.items()

    def check(t, path):
        if (a in t) == (b in t):
            raise _fail(path, f"exactly one of `{a}` ({what_a}) or `{b}` ({what_b})",
                        sorted(t))

    return check


@dataclasses.dataclass(frozen=True)
class Kind:
    """A torque or frame kind a scenario may name: its class `cls`, its table's keys
    `params` (name → `Param`), and `build`, which makes the object from the drawn and static
    values of the keys present (name → value); by default `cls(**values)`. `check` tests
    rules between keys (`check(table, path)` raises a `ScenarioError`); a `relative_only`
    kind needs `kind = "relative_rigid_body"`."""

    cls: type
    params: Mapping[str, Param] = dataclasses.field(default_factory=dict)
    build: Callable[[dict[str, Any]], eqx.Module] | None = None
    check: Callable[[dict, str], None] | None = None
    relative_only: bool = False

    def validate(self, x: Mapping, path: str) -> tuple[dict, dict]:
        """The table `x` at `path` (its `kind` already looked up) validated: its
        distributions and its static settings, by key."""
        required = {name for name, p in self.params.items() if p.required}
        t = _table(x, path, set(self.params) | {"kind"}, required)
        dists, static = {}, {}
        for name, p in self.params.items():
            if name in t:
                (static if p.static else dists)[name] = p.parse(t[name], f"{path}.{name}")
        if self.check is not None:
            self.check(t, path)
        return dists, static

    def make(self, values: dict[str, Any]) -> eqx.Module:
        """The torque or frame from its keys' values (name → drawn or static value)."""
        return self.cls(**values) if self.build is None else self.build(values)


def _restoring_moment(p):
    if "coeffs" in p:
        return RestoringMoment(PolynomialSinPsi(p["coeffs"], p.get("eps", jnp.asarray(1.0))))
    return RestoringMoment(p["k"], p.get("eps"))


def _gravity_gradient(p):
    if "eps" in p:
        return GravityGradient(p["eps"])
    return GravityGradient.from_orbit_rate(p["orbit_rate"])


def _euler_angle_frame(p):
    angles = HarmonicAngles(**{k: v for k, v in p.items() if k != "seq"})
    return EulerAngleFrame(angles, seq=p.get("seq", "ZXZ"))


TORQUES: dict[str, Kind] = {
    "body": Kind(BodyTorque, {"moment": _quantity_param((3,), required=True)}),
    "inertial": Kind(InertialTorque, {"moment": _quantity_param((3,), required=True)}),
    "uniform_gravity": Kind(UniformGravity, {"weight": _quantity_param(required=True),
                                             "com": _quantity_param((3,), required=True)}),
    "restoring_moment": Kind(
        RestoringMoment, {"k": _quantity_param(), "coeffs": Param(_coeffs),
                          "eps": _quantity_param()},
        build=_restoring_moment,
        check=_exactly_one(k="constant", coeffs="K(τ) polynomial")),
    "gravity_gradient": Kind(
        GravityGradient, {"eps": _quantity_param(), "orbit_rate": _quantity_param(positive=True)},
        build=_gravity_gradient,
        check=_exactly_one(eps="3μ/R³", orbit_rate="n, ε = 3n²")),
    "balancing_transport": Kind(BalancingTransport, relative_only=True),
}
"""The registry of torque kinds for `[[model.torques]]`: kind → `Kind` (the class, the
accepted keys and their validation, the builder). `Scenario.from_dict` validates a table
with it and `Scenario.build` builds from it; a kind not in it is an error in both, never a
fallback. Adding a torque usable from TOML is the torque class plus one entry here: nothing
else to edit."""
FRAMES: dict[str, Kind] = {
    "inertial": Kind(Inertial),
    "constant_rate": Kind(ConstantRate, {"omega_e": _quantity_param((3,), required=True),
                                         "quat0": _UNIT_QUAT}),
    "circular_orbit": Kind(CircularOrbit, {"n": _quantity_param(required=True),
                                           "quat0": _UNIT_QUAT}),
    "euler_angles": Kind(
        EulerAngleFrame,
        {"seq": Param(_euler_seq, static=True),
         **{k: _quantity_param((3,)) for k in ("offset", "rate", "amplitude", "frequency",
                                               "phase")}},
        build=_euler_angle_frame),
}
"""The registry of frame kinds for `[model.frame]`, as `TORQUES` is for torques: adding a
frame usable from TOML is the frame class plus one entry here."""


def _kind(registry: Mapping[str, Kind], kind: Any, path: str) -> Kind:
    """`registry[kind]`, or a `ScenarioError` at `path` listing the registered kinds."""
    if not isinstance(kind, str) or kind not in registry:
        raise _fail(path, f"one of {sorted(registry)}", kind)
    return registry[kind]


def _kinded(x, path, registry) -> tuple[str, dict, dict]:
    """A table with a `kind` from `registry`: the kind, its distributions and its static
    settings (by key)."""
    if not isinstance(x, Mapping) or "kind" not in x:
        raise _fail(f"{path}.kind", f"one of {sorted(registry)} (missing)")
    return x["kind"], *_kind(registry, x["kind"], f"{path}.kind").validate(x, path)


# ----------------------------------------------------------------------------------------
# Summaries: per-trajectory scalars computed in the compiled sweep from the saved states.
# ----------------------------------------------------------------------------------------


def _nutation(quat):
    """Angle between the body z-axis and the parent z-axis: arccos R33, R33 = 1 − 2(x²+y²)."""
    c = 1.0 - 2.0 * (quat[..., 1] ** 2 + quat[..., 2] ** 2)
    return jnp.arccos(jnp.clip(c, -1.0, 1.0))


def _first_flip(ts, omega, J):
    """First time the body rate along the intermediate principal axis of J changes sign
    (linear interpolation between output times), NaN if it never does within `ts`. For a
    spin started near the intermediate axis this is the first intermediate-axis flip."""
    _, axes = jnp.linalg.eigh(J)
    s = omega @ axes[:, 1]
    crossed = jnp.sign(s[1:]) * jnp.sign(s[0]) < 0
    k = jnp.argmax(crossed)
    frac = s[k] / (s[k] - s[k + 1])
    return jnp.where(jnp.any(crossed) & (s[0] != 0), ts[k] + frac * (ts[k + 1] - ts[k]), jnp.nan)


def _relative_drift(x):
    return jnp.max(jnp.abs(x - x[0])) / jnp.abs(x[0])


class Summary(NamedTuple):
    """A per-trajectory summary a scenario may keep: what it is, its units (UDUNITS, as the
    store's `units` attribute) and the function of `(model, trajectory)` computing it."""

    description: str
    units: str
    fn: Callable


SUMMARIES: dict[str, Summary] = {
    "max_nutation": Summary("largest angle between body z and parent z over the output times",
                            "rad", lambda m, tr: jnp.max(_nutation(tr.ys.quat))),
    "final_nutation": Summary("angle between body z and parent z at the last output time",
                              "rad", lambda m, tr: _nutation(tr.ys.quat[-1])),
    "energy_drift": Summary("max |E - E0| / |E0| over the output times (conservative models)",
                            "1", lambda m, tr: _relative_drift(invariants.energy(m, tr))),
    "relative_energy_drift": Summary(
        "max |T_r - T_r0| / T_r0 of the relative kinetic energy "
        "(docs/physics.md#balancing-transport-moment)", "1",
        lambda m, tr: _relative_drift(invariants.relative_kinetic_energy(m, tr))),
    "first_flip_time": Summary(
        "first sign change of omega along the intermediate principal axis (NaN: none)", "s",
        lambda m, tr: _first_flip(tr.ts, tr.ys.omega, m.inertia)),
    "min_abs_omega": Summary("smallest |omega| (|omega_r| in relative models) over the "
                             "output times", "rad/s",
                             lambda m, tr: jnp.min(jnp.linalg.norm(tr.ys.omega, axis=-1))),
    "max_abs_omega": Summary("largest |omega| (|omega_r| in relative models) over the "
                             "output times", "rad/s",
                             lambda m, tr: jnp.max(jnp.linalg.norm(tr.ys.omega, axis=-1))),
}
SOLVERS = ("Tsit5", "Dopri5", "Dopri8", "LiePoissonSplitting")
# The fixed-step, structure-preserving methods (`[solver] dt`, `order`); the others are
# diffrax's adaptive ones (`[solver] rtol`, `atol`).
FIXED_STEP = ("LiePoissonSplitting",)
_DTYPES = ("float64", "float32")


# ----------------------------------------------------------------------------------------
# Scenario
# ----------------------------------------------------------------------------------------


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
            d = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as e:
            raise ScenarioError(f"{path}: not valid TOML: {e}") from None
        return cls.from_dict(d, default_name=path.stem)

    @classmethod
    def load(cls, name_or_path: str | pathlib.Path) -> Scenario:
        """A shipped scenario by name (`list_scenarios()`), or a TOML file."""
        p = pathlib.Path(name_or_path)
        if not p.exists() and (SCENARIO_DIR / f"{name_or_path}.toml").exists():
            p = SCENARIO_DIR / f"{name_or_path}.toml"
        if not p.exists():
            raise ScenarioError(f"no scenario file {str(name_or_path)!r} and no shipped "
                                f"scenario of that name (shipped: {list_scenarios()})")
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

        m = _table(d["model"], "model", {"kind", "inertia", "torques", "frame"},
                   {"kind", "inertia"})
        kind = m["kind"]
        if kind not in ("rigid_body", "relative_rigid_body"):
            raise _fail("model.kind", '"rigid_body" or "relative_rigid_body"', kind)
        dists: dict[str, AbstractDistribution] = {
            "model.inertia": _inertia_spec(m["inertia"], "model.inertia")}
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
                raise _fail("model.frame", 'no frame for kind = "rigid_body" (use '
                            '"relative_rigid_body")', m["frame"])
            frame, fdists, fstatic = _kinded(m["frame"], "model.frame", FRAMES)
            add("model.frame", fdists, fstatic)
        for tkind in kinds:
            if TORQUES[tkind].relative_only and kind != "relative_rigid_body":
                raise _fail("model.torques", f'{tkind} only with kind = '
                            '"relative_rigid_body"', tkind)

        ini = _table(d["initial"], "initial", {"omega", "attitude"}, {"omega"})
        dists["initial.omega"] = _quantity(ini["omega"], "initial.omega", (3,))
        dists["initial.attitude"] = _attitude(ini.get("attitude", [1.0, 0.0, 0.0, 0.0]),
                                              "initial.attitude")

        tt = _table(d["time"], "time", {"t0", "t1", "n"}, {"t1", "n"})
        t0 = float(_number(tt.get("t0", 0.0), "time.t0"))
        t1 = float(_number(tt["t1"], "time.t1"))
        if not t1 > t0:
            raise _fail("time.t1", f"a time after t0 = {t0}", tt["t1"])
        n_times = int(_number(tt["n"], "time.n", integer=True))
        if n_times < 2:
            raise _fail("time.n", "an integer ≥ 2 (output times, linspace(t0, t1, n))",
                        tt["n"])

        s = _table(d.get("solver", {}), "solver",
                   {"method", "rtol", "atol", "max_steps", "dtype", "dt", "order"})
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
                    raise _fail(f"solver.{key}", f'no tolerance with method = "{method}" '
                                "(it takes fixed steps: give solver.dt)", s[key])
            if "dt" not in s:
                raise _fail("solver.dt", f'the fixed step of method = "{method}" (a number '
                            "> 0, in the unit of time)")
            dt = float(_number(s["dt"], "solver.dt", positive=True))
            if dt > t1 - t0:
                raise _fail("solver.dt", f"a step no longer than t1 − t0 = {t1 - t0:g}", dt)
            order = int(_number(s.get("order", 6), "solver.order", integer=True))
            if order not in SPLITTING_ORDERS:
                raise _fail("solver.order", " or ".join(map(str, SPLITTING_ORDERS)), order)
            steps = fixed_steps(t1 - t0, dt)
            # One more by default: the rounding of the step's times may leave a short last one.
            max_steps = int(_number(s.get("max_steps", steps + 1), "solver.max_steps",
                                    integer=True, positive=True))
            if max_steps < steps:
                raise _fail("solver.max_steps", f"at least the {steps} steps of dt over "
                            "[t0, t1] (or leave it out)", max_steps)
        else:
            for key in ("dt", "order"):
                if key in s:
                    raise _fail(f"solver.{key}", f"only with method = one of {list(FIXED_STEP)}"
                                " (an adaptive method chooses its steps)", s[key])
            default_tol = default_tolerance(dtype)  # 1e-8, or 1e-6 in float32
            rtol = float(_number(s.get("rtol", default_tol), "solver.rtol", positive=True))
            if rtol < min_rtol(dtype):  # the step-size control would compare with rounding
                raise _fail("solver.rtol", f"a number ≥ {min_rtol(dtype):.2g} with dtype = "
                            f'"{dtype}" (8 machine epsilons of {dtype}: a finer tolerance is '
                            "below its rounding)", rtol)
            atol = float(_number(s.get("atol", default_tol), "solver.atol", positive=True))
            max_steps = int(_number(s.get("max_steps", 16384), "solver.max_steps",
                                    integer=True, positive=True))

        o = _table(d.get("outputs", {}), "outputs", {"summaries", "trajectories"})
        trajectories = _trajectories(o.get("trajectories", "all"), "outputs.trajectories")
        summaries = o.get("summaries", ["max_nutation", "min_abs_omega", "max_abs_omega"])
        if not isinstance(summaries, list) or not all(isinstance(x, str) for x in summaries):
            raise _fail("outputs.summaries", f"a list of names from {sorted(SUMMARIES)}",
                        summaries)
        for x in summaries:
            if x not in SUMMARIES:
                raise _fail("outputs.summaries", f"names from {sorted(SUMMARIES)}", x)
        if len(set(summaries)) != len(summaries):
            raise _fail("outputs.summaries", "no repeated names", summaries)

        if dtype != "float64":
            dists = {p: UniformSO3(jnp.float32) if isinstance(v, UniformSO3)
                     else _as_dtype(v, dtype) for p, v in dists.items()}
        sc = cls(name=name, description=description, kind=kind, torques=tuple(kinds),
                 frame=frame, static=static, dists=dists, t0=t0, t1=t1, n_times=n_times,
                 solver=method, rtol=rtol, atol=atol, max_steps=max_steps, dtype=dtype,
                 summaries=tuple(summaries), trajectories=trajectories,
                 source=json.loads(json.dumps(dict(d))), dt=dt, order=order)
        sc._check_solver()
        sc._check_summaries()
        return sc

    def with_settings(self, *, dtype: str | None = None,
                      trajectories: str | int | None = None) -> Scenario:
        """This scenario with `[solver] dtype` and/or `[outputs] trajectories` set to the
        values given (`None` keeps the scenario's): its source with those keys replaced,
        validated again, so that a bad value, or a `solver.rtol` finer than the new dtype
        resolves, is a `ScenarioError` naming the key. The source, which a sweep store
        keeps, then holds the values the scenario runs with. Returns `self` when nothing
        changes."""
        source = json.loads(json.dumps(self.source))
        changed = False
        for table, key, value in (("solver", "dtype", dtype),
                                  ("outputs", "trajectories", trajectories)):
            # By type too: `True == 1`, and a bool must reach the validation (which refuses it).
            if value is not None and (value != getattr(self, key)
                                      or type(value) is not type(getattr(self, key))):
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

    def sample(self, dists: Mapping[str, AbstractDistribution], key,
               index) -> dict[str, jax.Array]:
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
            return model, Trajectory(ts=jnp.asarray(self.ts[:2]), ys=ys, stats={},
                                     result=RESULTS.successful)

        # Shapes only (nothing computed or compiled): what the summaries are traced with.
        model, traj = jax.eval_shape(nominal_run)
        for name in self.summaries:
            try:
                jax.eval_shape(lambda m, tr, f=SUMMARIES[name].fn: f(m, tr), model, traj)
            except (ValueError, NotImplementedError, AttributeError) as e:
                raise ScenarioError(f"`outputs.summaries`: {name!r} is not defined for this "
                                    f"model: {e}") from None


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
