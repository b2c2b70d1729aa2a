"""Monte Carlo sweeps: scenarios, chunked runs sharded over devices, streaming to disk, resume.

A **scenario** is a model, distributions of its parameters and of the initial conditions,
the output times, solver settings and the per-trajectory summaries to keep. It is written
in TOML (`Scenario.from_toml`, shipped ones in `rbdyn_jax/scenarios/`) or given as the same
nested dict (`Scenario.from_dict`), and validated: an unknown key or a bad value raises a
`ScenarioError` naming the key (`model.inertia.principal`) and what was expected.

`run(scenario, n, out)` draws trajectory `i` from `fold_in(key(seed), i)` (and every random
quantity from a further `fold_in` with a hash of its key path), so a trajectory's sample
does not depend on the chunking, the devices or the other random quantities. The solves run
through one compiled program: each device takes its part of a chunk with
`jax.shard_map` (no collectives inside the solver loop) and runs it through the lane solver
of `simulate_batch(..., lanes=lanes)`, in fixed blocks of 8 × `lanes` trajectories: `lanes`
trajectories step together, and a lane whose trajectory has finished takes the next one of
its block at once. Because the block shape is fixed and
every parameter enters as a runtime argument (nothing constant-folded), the results are
**bitwise identical for any chunk size and any number of devices** at a given `lanes`.
Each finished chunk is written to a zarr store (format 2 with consolidated metadata:
`xarray.open_zarr(path)` reads it) and dropped, so memory does not grow with `n`.

The store holds, with dims `trajectory × time × axis|quat_component`: `omega`, `quat`,
`inertia` (`trajectory × row × col`), `status` (a `RESULTS` code per trajectory; −1 = not
run yet), `num_steps`, and one variable per summary. `status` is written last in a chunk,
so a run that is killed keeps every finished chunk and `run(..., resume=True)` solves
exactly the trajectories still marked −1.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import shutil
import time
import tomllib
import zlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from . import inertia as _inertia
from . import invariants, rotation
from ._checks import checks_as_nan
from ._xla import jit
from .frames import CircularOrbit, ConstantRate, EulerAngleFrame, HarmonicAngles, Inertial
from .integrate import MODE_DEPENDENT_JITS, RESULTS, Trajectory, _lane_batch
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

SCENARIO_DIR = pathlib.Path(__file__).parent / "scenarios"
CONVENTIONS = (
    "PHYSICS.md conventions: quat = [w, x, y, z] (scalar first), unit, rotating body "
    "components into the parent frame (O0 for rigid_body, the transport frame O1 for "
    "relative_rigid_body); omega in body components, rad/s (the rate relative to O1 for "
    "relative_rigid_body); inertia in body axes; times in s; angles in rad."
)


class ScenarioError(ValueError):
    """A scenario file or dict that does not validate; the message names the key."""


# ----------------------------------------------------------------------------------------
# Distributions: eqx.Modules whose leaves are arrays, so they enter the compiled sweep as
# runtime arguments. `sample(key)` gives one draw.
# ----------------------------------------------------------------------------------------


class Fixed(eqx.Module):
    """Always `value`."""

    value: jax.Array

    def sample(self, key):
        return self.value


class Normal(eqx.Module):
    """Independent normal components, `mean + std · N(0, 1)`."""

    mean: jax.Array
    std: jax.Array

    def sample(self, key):
        return self.mean + self.std * jax.random.normal(key, self.mean.shape, self.mean.dtype)


class Uniform(eqx.Module):
    """Independent uniform components on `[low, high)`."""

    low: jax.Array
    high: jax.Array

    def sample(self, key):
        u = jax.random.uniform(key, self.low.shape, self.low.dtype)
        return self.low + (self.high - self.low) * u


class LogNormal(eqx.Module):
    """`median · exp(sigma · N(0, 1))`, componentwise (positive quantities)."""

    median: jax.Array
    sigma: jax.Array

    def sample(self, key):
        z = jax.random.normal(key, self.median.shape, self.median.dtype)
        return self.median * jnp.exp(self.sigma * z)


class UniformSO3(eqx.Module):
    """A uniformly distributed attitude: a normalised 4-D Gaussian (Haar measure on SO(3)),
    sign fixed to w ≥ 0."""

    dtype: Any = eqx.field(static=True, default=jnp.float64)

    def sample(self, key):
        q = jax.random.normal(key, (4,), self.dtype)
        q = q / jnp.linalg.norm(q)
        return jnp.where(q[0] < 0, -q, q)


class EulerAttitude(eqx.Module):
    """Attitude from Euler angles drawn from `angles` (a distribution) in sequence `seq`."""

    angles: eqx.Module
    seq: str = eqx.field(static=True)

    def sample(self, key):
        return rotation.euler_to_quat(self.angles.sample(key), self.seq)


class DispersedInertia(eqx.Module):
    """A physical inertia around `nominal`: the log-Cholesky coordinates θ of its planar
    tensor J' = L Lᵀ (`inertia.to_log_cholesky`) are perturbed, the log-diagonal by
    `sigma · N(0, 1)` and each off-diagonal `L_ij` by `sigma · sqrt(L_ii L_jj) · N(0, 1)`,
    a relative spread of about `sigma` in every moment and product of inertia. Every sample
    is physical (triangle inequalities hold) by construction (PHYSICS.md §3)."""

    nominal: jax.Array
    sigma: jax.Array

    def sample(self, key):
        theta = _inertia.to_log_cholesky(self.nominal)
        d = jnp.exp(theta[:3])
        scale = jnp.stack([1.0, 1.0, 1.0, jnp.sqrt(d[1] * d[0]), jnp.sqrt(d[2] * d[0]),
                           jnp.sqrt(d[2] * d[1])]).astype(theta.dtype)
        z = jax.random.normal(key, (6,), theta.dtype)
        return _inertia.from_log_cholesky(theta + self.sigma * scale * z)


def _path_key(key, path: str):
    return jax.random.fold_in(key, zlib.crc32(path.encode()) & 0x7FFFFFFF)


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


DISTRIBUTIONS = {
    "fixed": ({"value"}, lambda p, v: Fixed(v["value"])),
    "normal": ({"mean", "std"}, lambda p, v: Normal(v["mean"], v["std"])),
    "uniform": ({"low", "high"}, lambda p, v: Uniform(v["low"], v["high"])),
    "lognormal": ({"median", "sigma"}, lambda p, v: LogNormal(v["median"], v["sigma"])),
}


def _quantity(x, path, shape=(), *, positive=False) -> eqx.Module:
    """A literal (→ `Fixed`) or a distribution table `{dist = "normal", mean, std}` …"""
    if not isinstance(x, Mapping):
        return Fixed(jnp.asarray(_array(x, path, shape, positive=positive)))
    if "dist" not in x:
        raise _fail(f"{path}.dist", f"one of {sorted(DISTRIBUTIONS)} (missing)")
    kind = x["dist"]
    if kind not in DISTRIBUTIONS:
        raise _fail(f"{path}.dist", f"one of {sorted(DISTRIBUTIONS)}", kind)
    fields, make = DISTRIBUTIONS[kind]
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
    return make(path, vals)


def _quat_array(x, path) -> np.ndarray:
    q = _array(x, path, (4,))
    n = np.linalg.norm(q)
    if not abs(n - 1.0) < 1e-6:
        raise _fail(path, "a unit quaternion [w, x, y, z]", x)
    return q / n


def _attitude(x, path) -> eqx.Module:
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
    seq = t.get("seq", "ZXZ")
    try:
        rotation._parse_seq(seq)
    except (ValueError, TypeError):
        raise _fail(f"{path}.seq", "an Euler sequence such as \"ZXZ\" or \"xyz\"", seq) from None
    degrees = t.get("degrees", False)
    if not isinstance(degrees, bool):
        raise _fail(f"{path}.degrees", "true or false", degrees)
    angles = _quantity(t["euler"], f"{path}.euler", (3,))
    if degrees:  # every leaf (value, mean, std, low, high) is an angle
        angles = jax.tree_util.tree_map(lambda a: a * (np.pi / 180.0), angles)
    return EulerAttitude(angles, seq)


def _inertia_spec(x, path) -> eqx.Module:
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
                    "inequalities A + B ≥ C, PHYSICS.md §3) with no zero moment", x.get(
                        "principal", x.get("matrix")))
    sigma = _number(t.get("log_cholesky_sigma", 0.0), f"{path}.log_cholesky_sigma", nonneg=True)
    if sigma > 0 and not np.all(np.linalg.eigvalsh(np.asarray(_inertia.planar(J))) > 0):
        raise _fail(f"{path}.log_cholesky_sigma", "0 for a flat body (a zero planar moment, "
                    "A + B = C, has no log-Cholesky coordinates to disperse)", sigma)
    return DispersedInertia(jnp.asarray(J), jnp.asarray(float(sigma)))


# Torques: kind → (required, optional keys with shapes).
TORQUES: dict[str, tuple[dict[str, tuple], dict[str, tuple]]] = {
    "body": ({"moment": (3,)}, {}),
    "inertial": ({"moment": (3,)}, {}),
    "uniform_gravity": ({"weight": (), "com": (3,)}, {}),
    "restoring_moment": ({}, {"k": (), "coeffs": None, "eps": ()}),
    "gravity_gradient": ({}, {"eps": (), "orbit_rate": ()}),
    "balancing_transport": ({}, {}),
}
FRAMES = {
    "inertial": ({}, {}),
    "constant_rate": ({"omega_e": (3,)}, {"quat0": (4,)}),
    "circular_orbit": ({"n": ()}, {"quat0": (4,)}),
    "euler_angles": ({}, {"seq": None, "offset": (3,), "rate": (3,), "amplitude": (3,),
                          "frequency": (3,), "phase": (3,)}),
}


def _kinded(x, path, registry) -> tuple[str, dict, dict, dict]:
    """A table with a `kind` from `registry` (kind → (required, optional) keys): the kind,
    the validated table and its required and optional keys."""
    if not isinstance(x, Mapping) or "kind" not in x:
        raise _fail(f"{path}.kind", f"one of {sorted(registry)} (missing)")
    kind = x["kind"]
    if kind not in registry:
        raise _fail(f"{path}.kind", f"one of {sorted(registry)}", kind)
    req, opt = registry[kind]
    return kind, _table(x, path, set(req) | set(opt) | {"kind"}, set(req)), req, opt


def _torque_spec(x, path) -> tuple[str, dict]:
    kind, t, req, opt = _kinded(x, path, TORQUES)
    params = {}
    for name, shape in {**req, **opt}.items():
        if name not in t:
            continue
        if name == "coeffs":
            n = len(t[name]) if isinstance(t[name], list) else 0
            if n < 1:
                raise _fail(f"{path}.coeffs", "a non-empty list of numbers (K(τ) = Σ c_i τ^i)",
                            t[name])
            shape = (n,)
        params[name] = _quantity(t[name], f"{path}.{name}", shape,
                                 positive=name in ("orbit_rate",))
    if kind == "restoring_moment" and ("k" in t) == ("coeffs" in t):
        raise _fail(path, "exactly one of `k` (constant) or `coeffs` (K(τ) polynomial)",
                    sorted(t))
    if kind == "gravity_gradient" and ("eps" in t) == ("orbit_rate" in t):
        raise _fail(path, "exactly one of `eps` (3μ/R³) or `orbit_rate` (n, ε = 3n²)",
                    sorted(t))
    return kind, params


def _frame_spec(x, path) -> tuple[str, dict, str]:
    kind, t, req, opt = _kinded(x, path, FRAMES)
    params, seq = {}, "ZXZ"
    for name, shape in {**req, **opt}.items():
        if name not in t:
            continue
        if name == "seq":
            seq = t["seq"]
            try:
                rotation._parse_seq(seq)
            except (ValueError, TypeError):
                raise _fail(f"{path}.seq", "an Euler sequence such as \"ZXZ\"", seq) from None
        elif name == "quat0":
            params[name] = Fixed(jnp.asarray(_quat_array(t[name], f"{path}.quat0")))
        else:
            params[name] = _quantity(t[name], f"{path}.{name}", shape)
    return kind, params, seq


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


SUMMARIES: dict[str, tuple[str, Callable]] = {
    "max_nutation": ("largest angle between body z and parent z over the output times, rad",
                     lambda m, tr: jnp.max(_nutation(tr.ys.quat))),
    "final_nutation": ("angle between body z and parent z at the last output time, rad",
                       lambda m, tr: _nutation(tr.ys.quat[-1])),
    "energy_drift": ("max |E − E0| / |E0| over the output times (conservative models)",
                     lambda m, tr: _relative_drift(invariants.energy(m, tr))),
    "relative_energy_drift": ("max |T_r − T_r0| / T_r0, relative kinetic energy (PHYSICS §5)",
                              lambda m, tr: _relative_drift(
                                  invariants.relative_kinetic_energy(m, tr))),
    "first_flip_time": ("first sign change of ω along the intermediate principal axis, s",
                        lambda m, tr: _first_flip(tr.ts, tr.ys.omega, m.inertia)),
    "min_abs_omega": ("smallest |ω| (|ω_r| in relative models) over the output times, rad/s",
                      lambda m, tr: jnp.min(jnp.linalg.norm(tr.ys.omega, axis=-1))),
    "max_abs_omega": ("largest |ω| (|ω_r| in relative models) over the output times, rad/s",
                      lambda m, tr: jnp.max(jnp.linalg.norm(tr.ys.omega, axis=-1))),
}
SOLVERS = ("Tsit5", "Dopri5", "Dopri8")


# ----------------------------------------------------------------------------------------
# Scenario
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A validated sweep scenario (build with `from_toml`, `from_dict` or `load`).

    `dists` is the pytree of distributions (key path → distribution module); the structure
    (model kind, torques, frame, summaries) is static. See `rbdyn_jax/scenarios/*.toml` and
    the README for the format; `TORQUES`, `FRAMES`, `DISTRIBUTIONS` and `SUMMARIES` list
    the accepted kinds.
    """

    name: str
    description: str
    kind: str
    torques: tuple[str, ...]
    frame: str
    frame_seq: str
    dists: dict[str, eqx.Module]
    t0: float
    t1: float
    n_times: int
    solver: str
    rtol: float
    atol: float
    max_steps: int
    summaries: tuple[str, ...]
    source: dict

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
        dists: dict[str, eqx.Module] = {"model.inertia": _inertia_spec(m["inertia"],
                                                                        "model.inertia")}
        torques = m.get("torques", [])
        if not isinstance(torques, list):
            raise _fail("model.torques", "an array of tables ([[model.torques]])", torques)
        kinds = []
        for i, tq in enumerate(torques):
            tkind, params = _torque_spec(tq, f"model.torques[{i}]")
            kinds.append(tkind)
            dists.update({f"model.torques[{i}].{k}": v for k, v in params.items()})
        frame, seq = "inertial", "ZXZ"
        if "frame" in m:
            if kind != "relative_rigid_body":
                raise _fail("model.frame", 'no frame for kind = "rigid_body" (use '
                            '"relative_rigid_body")', m["frame"])
            frame, params, seq = _frame_spec(m["frame"], "model.frame")
            dists.update({f"model.frame.{k}": v for k, v in params.items()})
        if "balancing_transport" in kinds and kind != "relative_rigid_body":
            raise _fail("model.torques", 'balancing_transport only with kind = '
                        '"relative_rigid_body"', "balancing_transport")

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

        s = _table(d.get("solver", {}), "solver", {"method", "rtol", "atol", "max_steps"})
        method = s.get("method", "Tsit5")
        if method not in SOLVERS:
            raise _fail("solver.method", f"one of {list(SOLVERS)}", method)
        rtol = float(_number(s.get("rtol", 1e-8), "solver.rtol", positive=True))
        atol = float(_number(s.get("atol", 1e-8), "solver.atol", positive=True))
        max_steps = int(_number(s.get("max_steps", 16384), "solver.max_steps", integer=True,
                                positive=True))

        o = _table(d.get("outputs", {}), "outputs", {"summaries"})
        summaries = o.get("summaries", ["max_nutation", "min_abs_omega", "max_abs_omega"])
        if not isinstance(summaries, list) or not all(isinstance(x, str) for x in summaries):
            raise _fail("outputs.summaries", f"a list of names from {sorted(SUMMARIES)}",
                        summaries)
        for x in summaries:
            if x not in SUMMARIES:
                raise _fail("outputs.summaries", f"names from {sorted(SUMMARIES)}", x)
        if len(set(summaries)) != len(summaries):
            raise _fail("outputs.summaries", "no repeated names", summaries)

        sc = cls(name=name, description=description, kind=kind, torques=tuple(kinds),
                 frame=frame, frame_seq=seq, dists=dists, t0=t0, t1=t1, n_times=n_times,
                 solver=method, rtol=rtol, atol=atol, max_steps=max_steps,
                 summaries=tuple(summaries), source=json.loads(json.dumps(dict(d))))
        sc._check_summaries()
        return sc

    # -- building one trajectory ----------------------------------------------------------

    @property
    def ts(self) -> np.ndarray:
        return np.linspace(self.t0, self.t1, self.n_times)

    def nominal(self) -> dict[str, jax.Array]:
        """The centre of every distribution (its mean, median or fixed value)."""
        return _centres(self.dists)

    def build(self, values: Mapping[str, jax.Array]) -> tuple[eqx.Module, State]:
        """The model and initial state for one set of drawn `values` (key path → value)."""
        torques = []
        for i, kind in enumerate(self.torques):
            get = lambda k, i=i: values.get(f"model.torques[{i}].{k}")  # noqa: E731
            if kind == "body":
                torques.append(BodyTorque(get("moment")))
            elif kind == "inertial":
                torques.append(InertialTorque(get("moment")))
            elif kind == "uniform_gravity":
                torques.append(UniformGravity(get("weight"), get("com")))
            elif kind == "restoring_moment":
                if get("coeffs") is not None:
                    eps = get("eps") if get("eps") is not None else jnp.asarray(1.0)
                    torques.append(RestoringMoment(PolynomialSinPsi(get("coeffs"), eps)))
                else:
                    torques.append(RestoringMoment(get("k"), get("eps")))
            elif kind == "gravity_gradient":
                torques.append(GravityGradient(get("eps")) if get("eps") is not None
                               else GravityGradient.from_orbit_rate(get("orbit_rate")))
            else:
                torques.append(BalancingTransport())
        torque = None
        for tq in torques:
            torque = tq if torque is None else torque + tq
        J = values["model.inertia"]
        y0 = State(omega=values["initial.omega"], quat=values["initial.attitude"])
        if self.kind == "rigid_body":
            return RigidBody(J, torque), y0
        fv = lambda k: values.get(f"model.frame.{k}")  # noqa: E731
        if self.frame == "inertial":
            frame = Inertial()
        elif self.frame == "constant_rate":
            frame = ConstantRate(fv("omega_e"), fv("quat0"))
        elif self.frame == "circular_orbit":
            frame = CircularOrbit(fv("n"), fv("quat0"))
        else:
            zero = jnp.zeros(3)
            parts = {k: fv(k) if fv(k) is not None else zero
                     for k in ("offset", "rate", "amplitude", "frequency", "phase")}
            frame = EulerAngleFrame(HarmonicAngles(**parts), seq=self.frame_seq)
        return RelativeRigidBody(J, frame, torque), y0

    def sample(self, dists: Mapping[str, eqx.Module], key, index) -> dict[str, jax.Array]:
        """The drawn values of trajectory `index` (traceable)."""
        k = jax.random.fold_in(key, index)
        return {path: dist.sample(_path_key(k, path)) for path, dist in dists.items()}

    def _check_summaries(self):
        model, y0 = self.build(self.nominal())
        ts = jnp.asarray(self.ts[:2])
        ys = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), y0)
        traj = Trajectory(ts=ts, ys=ys, stats={}, result=RESULTS.successful)
        for name in self.summaries:
            try:
                jax.eval_shape(lambda m, tr, f=SUMMARIES[name][1]: f(m, tr), model, traj)
            except (ValueError, NotImplementedError, AttributeError) as e:
                raise ScenarioError(f"`outputs.summaries`: {name!r} is not defined for this "
                                    f"model: {e}") from None


def _centre(dist):
    """The centre of a distribution: its fixed value, mean, mid-point or median."""
    if isinstance(dist, Fixed):
        return dist.value
    if isinstance(dist, Normal):
        return dist.mean
    if isinstance(dist, Uniform):
        return 0.5 * (dist.low + dist.high)
    if isinstance(dist, LogNormal):
        return dist.median
    if isinstance(dist, DispersedInertia):
        return dist.nominal
    if isinstance(dist, EulerAttitude):
        return rotation.euler_to_quat(_centre(dist.angles), dist.seq)
    return jnp.array([1.0, 0.0, 0.0, 0.0])  # UniformSO3


def _centres(dists: Mapping[str, eqx.Module]) -> dict[str, jax.Array]:
    return {path: _centre(d) for path, d in dists.items()}


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in `rbdyn_jax/scenarios/`."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


# ----------------------------------------------------------------------------------------
# The compiled chunk solver
# ----------------------------------------------------------------------------------------

def _solve_block(scenario: Scenario, dists, key, idx, tols, lanes):
    """Sample and solve the trajectories `idx` (through `lanes` lanes of the lane solver);
    per-trajectory outputs."""
    import diffrax

    values = jax.vmap(lambda i: scenario.sample(dists, key, i))(idx)
    # A non-finite draw (an overflowing lognormal, …) would fail the model's checks for the
    # whole block: solve the nominal values in its lane instead and mark it non-finite.
    ok = jnp.ones(idx.shape, bool)
    for v in values.values():
        ok = ok & jnp.all(jnp.isfinite(v.reshape(v.shape[0], -1)), axis=-1)
    nominal = _centres(dists)

    def lane(x):
        return ok.reshape((-1,) + (1,) * (x.ndim - 1))

    values = {p: jnp.where(lane(v), v, nominal[p]) for p, v in values.items()}
    models, y0s = jax.vmap(scenario.build)(values)
    ts = jnp.linspace(scenario.t0, scenario.t1, scenario.n_times)
    solver = getattr(diffrax, scenario.solver)()
    traj = _lane_batch(models, y0s, ts, solver, tols[0], tols[1], scenario.max_steps, lanes)
    status = jnp.where(ok, traj.result._value, RESULTS.nonfinite_state._value)

    def summaries(m, tr):
        return {name: SUMMARIES[name][1](m, tr) for name in scenario.summaries}

    summ = jax.vmap(summaries)(models, traj)
    good = status == 0
    out = {"omega": traj.ys.omega, "quat": traj.ys.quat, "inertia": models.inertia}
    out = {k: jnp.where(lane(v) if k == "inertia" else good[:, None, None], v, jnp.nan)
           for k, v in out.items()}
    return {
        **out,
        "status": status.astype(jnp.int32),
        "num_steps": traj.stats["num_steps"].astype(jnp.int64),
        **{k: jnp.where(good, v, jnp.nan) for k, v in summ.items()},
    }


_PER_LANE = 8  # trajectories per lane in one lane-solver block (a block: 8 × lanes)


@dataclasses.dataclass
class _Runner:
    """The compiled chunk solver: every call has the same padded size (one compilation)."""

    scenario: Scenario
    lanes: int
    devices: list
    chunk: int
    fn: Callable = dataclasses.field(init=False)
    mesh: Any = dataclasses.field(init=False)

    def __post_init__(self):
        sc, lanes = self.scenario, self.lanes
        self.mesh = jax.sharding.Mesh(np.asarray(self.devices), ("batch",))

        def per_device(idx, dists, key, tols):
            # Fixed blocks of _PER_LANE × lanes trajectories, one after the other: the
            # block's program is then the same for every chunk size and device count, so
            # the results are bitwise identical across them (a lane-solver loop over the
            # whole share compiles differently for each share size and rounds differently).
            # Fixed blocks also keep a share of 2048 on 2 XLA:CPU host devices from hanging
            # in the XLA runtime, as one loop over it did (all threads asleep).
            out = jax.lax.map(lambda b: _solve_block(sc, dists, key, b, tols, lanes),
                              idx.reshape(-1, _PER_LANE * lanes))
            return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

        # No collectives inside the solver loop: each device runs its own while loops.
        sharded = jax.shard_map(per_device, mesh=self.mesh,
                                in_specs=(P("batch"), P(), P(), P()), out_specs=P("batch"),
                                check_vma=False)
        self.fn = jit(sharded)

    @property
    def size(self) -> int:
        """The padded chunk: a multiple of _PER_LANE × lanes × devices."""
        quantum = _PER_LANE * self.lanes * len(self.devices)
        return -(-self.chunk // quantum) * quantum

    def __call__(self, idx: np.ndarray, key) -> dict[str, np.ndarray]:
        n = len(idx)  # ≤ chunk; padded with copies of the last index (solved, then dropped)
        full = np.concatenate([idx, np.full(self.size - n, idx[-1], idx.dtype)])
        arr = jax.make_array_from_callback(
            (self.size,), NamedSharding(self.mesh, P("batch")), lambda i: full[i])
        tols = jnp.asarray([self.scenario.rtol, self.scenario.atol])
        with checks_as_nan(jitted=MODE_DEPENDENT_JITS):  # traced on the first call only
            out = self.fn(arr, self.scenario.dists, key, tols)
        if jax.process_count() > 1:  # multi-host: every process gets the whole chunk
            from jax.experimental import multihost_utils

            out = multihost_utils.process_allgather(out, tiled=True)
        return {k: np.asarray(v)[:n] for k, v in out.items()}


_RUNNERS: dict[tuple, _Runner] = {}


def _runner(sc: Scenario, lanes: int, devices: tuple, chunk: int) -> _Runner:
    """A compiled runner, reused by later runs of the same scenario and layout (a resumed
    or repeated run in the same process compiles nothing)."""
    quantum = _PER_LANE * lanes * len(devices)  # the compiled shape: the padded chunk
    key = (json.dumps(sc.source, sort_keys=True), lanes, devices, -(-chunk // quantum))
    if key not in _RUNNERS:
        _RUNNERS.clear()  # keep one: a compiled solver holds memory
        _RUNNERS[key] = _Runner(sc, lanes, list(devices), chunk)
    return _RUNNERS[key]


# ----------------------------------------------------------------------------------------
# The store
# ----------------------------------------------------------------------------------------

_DIMS = {
    "omega": ("trajectory", "time", "axis"),
    "quat": ("trajectory", "time", "quat_component"),
    "inertia": ("trajectory", "row", "col"),
    "status": ("trajectory",),
    "num_steps": ("trajectory",),
}


def _status_codes() -> dict[str, str]:
    codes = {"-1": "not_run"}
    codes.update({str(item._value): name for name, item in RESULTS._name_to_item.items()})
    return codes


def _create_store(path: pathlib.Path, sc: Scenario, n: int, chunk: int, seed: int, lanes: int):
    import zarr

    from . import __version__

    g = zarr.open_group(str(path), mode="w", zarr_format=2)
    T = sc.n_times
    shapes = {"omega": (n, T, 3), "quat": (n, T, 4), "inertia": (n, 3, 3), "status": (n,),
              "num_steps": (n,)}
    dtypes = {"status": "int32", "num_steps": "int64"}
    for name in [*shapes, *sc.summaries]:
        shape = shapes.get(name, (n,))
        dims = _DIMS.get(name, ("trajectory",))
        fill = None if name in ("status", "num_steps") else np.nan
        a = g.create_array(name, shape=shape, chunks=(min(chunk, n),) + shape[1:],
                           dtype=dtypes.get(name, "float64"), fill_value=fill)
        attrs = {"_ARRAY_DIMENSIONS": list(dims)}
        if name in SUMMARIES:
            attrs["description"] = SUMMARIES[name][0]
        a.attrs.update(attrs)
    for start in range(0, n, 1 << 20):  # status −1 = not run (written, not a fill value)
        g["status"][start:start + (1 << 20)] = -1
    for name, values, dims in (("time", sc.ts, ["time"]),
                               ("trajectory", np.arange(n, dtype=np.int64), ["trajectory"])):
        a = g.create_array(name, shape=values.shape, chunks=(min(len(values), 1 << 20),),
                           dtype=values.dtype, fill_value=None)
        a[:] = values
        a.attrs["_ARRAY_DIMENSIONS"] = dims
    g["omega"].attrs["description"] = "body angular velocity (relative to O1 in relative models)"
    g["quat"].attrs["description"] = "attitude quaternion [w, x, y, z], body → parent"
    g.attrs.update({
        "title": f"rbdyn_jax Monte Carlo sweep: {sc.name}",
        "scenario_name": sc.name,
        "scenario": json.dumps(sc.source),
        "model_kind": sc.kind,
        "seed": seed,
        "n_trajectories": n,
        "chunk": chunk,
        "lanes": lanes,
        "summaries": list(sc.summaries),
        "status_codes": json.dumps(_status_codes()),
        "conventions": CONVENTIONS,
        "rbdyn_jax_version": __version__,
        "jax_version": jax.__version__,
        "complete": False,
    })
    zarr.consolidate_metadata(str(path))
    return g


def _open_store(path: pathlib.Path, sc: Scenario, n: int, seed: int, lanes: int):
    import zarr

    g = zarr.open_group(str(path), mode="r+", zarr_format=2)
    want = {"scenario": json.dumps(sc.source), "n_trajectories": n, "seed": seed,
            "lanes": lanes}
    for k, v in want.items():
        if g.attrs.get(k) != v:
            raise ValueError(f"cannot resume {path}: its {k} is {g.attrs.get(k)!r}, this run's "
                             f"is {v!r}; use a new --out or drop --resume.")
    return g


def _write_chunk(g, start: int, out: dict[str, np.ndarray]):
    stop = start + len(out["status"])
    for name, values in out.items():
        if name != "status":
            g[name][start:stop] = values
    g["status"][start:stop] = out["status"]  # last: marks the chunk done


# ----------------------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass
class Progress:
    """What `run` reports after each chunk (to an optional `progress` callback)."""

    done: int
    total: int
    failed: int
    elapsed: float
    solved_now: int


def _todo_chunks(status: np.ndarray, chunk: int) -> Iterator[tuple[int, np.ndarray]]:
    """(start, indices) of the chunks that still hold unrun trajectories."""
    for start in range(0, len(status), chunk):
        idx = np.nonzero(status[start:start + chunk] < 0)[0]
        if idx.size:
            yield start, start + idx


def run(
    scenario: Scenario | str | pathlib.Path,
    n: int,
    out: str | pathlib.Path,
    *,
    chunk: int = 1024,
    seed: int = 0,
    devices: int | None = None,
    lanes: int = 64,
    resume: bool = False,
    progress: Callable[[Progress], None] | None = None,
) -> pathlib.Path:
    """Run `n` trajectories of `scenario` and stream them to the zarr store `out`.

    **Arguments:**
    - `scenario`: a `Scenario`, a shipped scenario name or a TOML path.
    - `n`: number of trajectories; `chunk`: trajectories solved and written at a time
      (memory ∝ chunk); `seed`: the random seed. Each device solves its share in blocks
      of 8 × `lanes`, so a chunk is padded to a multiple of 8 × `lanes` × devices (1024
      at the defaults on two devices): a smaller chunk solves padding (chunk 256 measured
      3.9× slower than 1024).
    - `devices`: how many of `jax.devices()` to shard each chunk over (default all).
    - `lanes`: lanes of each device's solver loop (the lane solver of `simulate_batch`; a
      lane takes the next trajectory as soon as its own has finished). Results are bitwise
      identical for any `chunk` and `devices` at the same `lanes`.
    - `resume`: continue an interrupted run in `out` (same scenario, n, seed, lanes),
      solving only the trajectories not yet written.
    - `progress`: called with a `Progress` after every chunk.

    **Returns:** the path of the store; open it with `open_dataset(path)`.
    """
    sc = scenario if isinstance(scenario, Scenario) else Scenario.load(scenario)
    for name, v in (("n", n), ("chunk", chunk), ("lanes", lanes)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
            raise ValueError(f"`{name}` must be a positive integer, got {v!r}.")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}.")
    if not jax.config.jax_enable_x64:
        raise ValueError("sweeps run in float64: call "
                         "`jax.config.update('jax_enable_x64', True)` first.")
    import zarr

    all_devices = jax.devices()
    devices = len(all_devices) if devices is None else devices
    if isinstance(devices, bool) or not 1 <= devices <= len(all_devices):
        raise ValueError(f"`devices` must be in 1..{len(all_devices)} (jax.devices()), "
                         f"got {devices!r}.")
    path = pathlib.Path(out)
    # Multi-host (after `jax.distributed.initialize()`): every process runs this function
    # on the same arguments, the chunks are sharded over all hosts' devices, and process 0
    # alone writes the store (a filesystem all hosts see).
    writer = jax.process_index() == 0
    if writer:
        _prepare_store(path, sc, n, chunk, seed, lanes, resume)
    _barrier("rbdyn_jax.sweep: store ready")
    g = zarr.open_group(str(path), mode="r+" if writer else "r", zarr_format=2)

    runner = _runner(sc, lanes, tuple(all_devices[:devices]), chunk)
    key = jax.random.key(seed)
    status = g["status"][:]
    done = int(np.sum(status >= 0))
    failed = int(np.sum(status > 0))
    t_start = time.perf_counter()
    for _, idx in _todo_chunks(status, chunk):
        res = runner(idx, key)
        if writer:  # one write per contiguous run (a partly finished chunk has several)
            runs = np.split(np.arange(idx.size), np.nonzero(np.diff(idx) != 1)[0] + 1)
            for r in runs:
                _write_chunk(g, int(idx[r[0]]), {k: v[r[0]:r[-1] + 1] for k, v in res.items()})
        done += idx.size
        failed += int(np.sum(res["status"] != 0))
        if progress is not None:
            progress(Progress(done, n, failed, time.perf_counter() - t_start, idx.size))
    if writer:
        g.attrs["complete"] = True
        zarr.consolidate_metadata(str(path))
    _barrier("rbdyn_jax.sweep: done")
    return path


def _barrier(name: str) -> None:
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def _prepare_store(path: pathlib.Path, sc: Scenario, n, chunk, seed, lanes, resume) -> None:
    """Check a store to resume, or build a new one beside `path` and rename it into place,
    so a store at `path` is always initialised (every status −1) and a kill at any moment
    leaves something `resume` can finish."""
    if resume and (path / ".zgroup").exists():
        _open_store(path, sc, n, seed, lanes)
        return
    if path.exists() and not (path / ".zgroup").exists() and any(path.iterdir()):
        raise ValueError(f"{path} exists and is not a sweep store; choose another --out.")
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    _create_store(tmp, sc, n, chunk, seed, lanes)
    shutil.rmtree(path, ignore_errors=True)
    os.replace(tmp, path)


def open_dataset(path: str | pathlib.Path):
    """The sweep store at `path` as an `xarray.Dataset` (lazy; nothing is loaded)."""
    import xarray as xr

    return xr.open_zarr(str(path))


def summarize(path: str | pathlib.Path, quantiles=(0.05, 0.5, 0.95)) -> dict:
    """Counts per status and, for every summary, count/mean/std/min/quantiles/max over the
    successful trajectories (finite values). Reads only the `(trajectory,)` columns (8 bytes
    per trajectory per summary), never the trajectories themselves."""
    import zarr

    g = zarr.open_group(str(path), mode="r")
    status = g["status"][:]
    codes = json.loads(g.attrs["status_codes"])
    counts = {codes.get(str(c), str(c)): int(k) for c, k in zip(*np.unique(status,
                                                                          return_counts=True))}
    stats = {}
    ok = status == 0
    for name in g.attrs["summaries"]:
        x = g[name][:][ok]
        x = x[np.isfinite(x)]
        row = {"count": int(x.size)}
        if x.size:
            row.update(mean=float(x.mean()), std=float(x.std(ddof=1)) if x.size > 1 else 0.0,
                       min=float(x.min()), max=float(x.max()))
            row.update({f"q{round(100 * q):02d}": float(v)
                        for q, v in zip(quantiles, np.quantile(x, quantiles))})
        stats[name] = row
    return {"n": int(status.size), "status": counts, "summaries": stats,
            "scenario": g.attrs["scenario_name"], "complete": bool(g.attrs["complete"])}


__all__ = [
    "DispersedInertia",
    "Fixed",
    "LogNormal",
    "Normal",
    "Progress",
    "Scenario",
    "ScenarioError",
    "SUMMARIES",
    "Uniform",
    "UniformSO3",
    "list_scenarios",
    "open_dataset",
    "run",
    "summarize",
]
