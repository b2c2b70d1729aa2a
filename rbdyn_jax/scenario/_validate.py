"""`ScenarioError` and the validation of a scenario's values (tables, numbers, arrays,
quantities, attitudes, the inertia): every error names the dotted key path and what was
expected."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import inertia as _inertia
from .._vector import parse_seq
from ._distributions import (
    DISTRIBUTIONS,
    AbstractDistribution,
    DispersedInertia,
    EulerAttitude,
    Fixed,
    LogNormal,
    UniformSO3,
)


class ScenarioError(ValueError):
    """A scenario file or dict that does not validate; the message names the key."""


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
        raise _fail(f"{path}.dist", "a positive distribution (fixed, uniform or lognormal)", kind)
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
        raise _fail(path, 'an Euler sequence such as "ZXZ" or "xyz"', x) from None
    return x


def _attitude(x, path) -> AbstractDistribution:
    if isinstance(x, list):
        return Fixed(jnp.asarray(_quat_array(x, path)))
    t = _table(x, path, {"dist", "quat", "euler", "seq", "degrees"})
    given = [k for k in ("dist", "quat", "euler") if k in t]
    if len(given) != 1:
        raise _fail(path, 'exactly one of `dist = "uniform_so3"`, `quat` or `euler`', sorted(t))
    if "dist" in t:
        if t["dist"] != "uniform_so3" or set(t) != {"dist"}:
            raise _fail(f"{path}.dist", '"uniform_so3" (alone; use `euler` for others)', t["dist"])
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
    if degrees:  # every leaf is an angle (value, mean, std, low, high, median) but σ
        sigma = angles.sigma if isinstance(angles, LogNormal) else None  # of log(angle)
        angles = jax.tree_util.tree_map(lambda a: a * (np.pi / 180.0), angles)
        if sigma is not None:
            angles = eqx.tree_at(lambda d: d.sigma, angles, sigma)
    return EulerAttitude(angles, seq)


def _trajectories(x, path) -> str | int:
    if isinstance(x, str) and x in ("all", "none"):
        return x
    if isinstance(x, int) and not isinstance(x, bool) and x >= 1:
        return x
    raise _fail(
        path, '"all", "none" or a positive integer K (the states of trajectories 0, K, 2K, …)', x
    )


def _physical(J: np.ndarray) -> bool:
    """Whether the symmetric `J` is physical (`inertia.check_inertia`, which checks a
    physical `J` in NumPy: loading a scenario compiles nothing)."""
    try:
        _inertia.check_inertia(J)
    except eqx.EquinoxRuntimeError:
        return False
    return True


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
    if not _physical(J) or not np.all(np.linalg.eigvalsh(J) > 0):
        raise _fail(
            key,
            "a physical inertia (positive moments obeying the triangle "
            "inequalities A + B ≥ C, docs/physics.md#physical-consistency) with no "
            "zero moment",
            x.get("principal", x.get("matrix")),
        )
    sigma = _number(t.get("log_cholesky_sigma", 0.0), f"{path}.log_cholesky_sigma", nonneg=True)
    planar = 0.5 * np.trace(J) * np.eye(3) - J  # J' (docs/physics.md#planar-inertia-tensor)
    if sigma > 0 and not np.all(np.linalg.eigvalsh(planar) > 0):
        raise _fail(
            f"{path}.log_cholesky_sigma",
            "0 for a flat body (a zero planar moment, "
            "A + B = C, has no log-Cholesky coordinates to disperse)",
            sigma,
        )
    return DispersedInertia(jnp.asarray(J), jnp.asarray(float(sigma)))
