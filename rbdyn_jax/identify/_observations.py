"""Observed records of K trajectories: `Observations`, checked once when built, and read
from a file by `Observations.from_file` (`_observation_files`)."""

import pathlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .. import rotation
from ._observation_files import read_fields

_UNIT_TOL = 1e-6  # |q| within this of 1: renormalised silently


def _as_np(x, name):
    if np.iscomplexobj(x):  # a cast would drop the imaginary part
        raise ValueError(f"`{name}` must be real, got dtype {np.asarray(x).dtype}.")
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"`{name}` must be a real array, got {type(x).__name__}.") from e
    return a


def _fill_times(t: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """Replace the times of masked samples so the row is strictly increasing (the solver
    saves there; their residuals are masked out)."""
    idx = np.flatnonzero(valid)
    if idx.size < 2:
        raise ValueError(f"`ts`: trajectory {k} has fewer than 2 unmasked samples.")
    tv = t[idx]
    if not np.all(np.isfinite(tv)):
        raise ValueError(f"`ts`: trajectory {k} has a non-finite time at an unmasked sample.")
    if np.any(np.diff(tv) <= 0):
        raise ValueError(f"`ts` must be strictly increasing; trajectory {k} is not.")
    out = np.interp(np.arange(t.size), idx, tv)  # interior gaps: linear in the index
    span = tv[-1] - tv[0]
    delta = 1e-9 * span
    before, after = np.arange(t.size) < idx[0], np.arange(t.size) > idx[-1]
    out[before] = tv[0] - delta * (idx[0] - np.flatnonzero(before))
    out[after] = tv[-1] + delta * (np.flatnonzero(after) - idx[-1])
    return out


def _sigma(s, shape, name):
    if s is None:
        return np.ones(shape)
    a = _as_np(s, name)
    try:
        a = np.broadcast_to(a, shape)
    except ValueError as e:
        raise ValueError(f"`{name}` of shape {a.shape} does not broadcast to {shape}.") from e
    if not np.all(np.isfinite(a) & (a > 0)):
        raise ValueError(f"`{name}` must be finite and positive.")
    return np.array(a)


class Observations(eqx.Module):
    """Observed records of K trajectories, n samples each (checked eagerly, in NumPy).

    **Arguments:**

    - `ts`: `(n,)` times shared by every trajectory, or `(K, n)` per trajectory. Over the
      unmasked samples of each trajectory they must be finite and strictly increasing
      (`ValueError` otherwise). Times of masked samples are ignored and replaced (interior:
      linear interpolation in the sample index; padding before/after: 1e-9 × span apart) so
      that the solver can save there.
    - `omega`: `(K, n, 3)` observed body angular velocity, or `None`.
    - `quat`: `(K, n, 4)` observed attitude body → parent, scalar first, or `None`. Sign is
      irrelevant. Quaternions whose norm is within 1e-6 of 1 are renormalised; any other
      norm (zero included) at an unmasked sample is a `ValueError`, unless
      `normalize_quat=True`, which renormalises every non-zero quaternion.
    - `sigma_omega`: noise standard deviation of each ω component, broadcast to `(K, n, 3)`
      (default 1).
    - `sigma_quat`: noise standard deviation (radians) of each component of the attitude
      error's rotation vector, broadcast to `(K, n)` (default 1).
    - `mask`: `(K, n)` booleans, `False` for padding (trajectories of different lengths);
      default all `True`.
    - `euler`, `seq`, `degrees`: the attitude as Euler angles `(K, n, 3)` of sequence `seq`
      (scipy conventions, default "ZXZ" = (ψ, θ, φ)) instead of `quat`; converted to unit
      quaternions (the residual is the same geodesic angle, free of the angles'
      singularities).
    - `nan_policy`: `"raise"` (default): a NaN/inf sample at an unmasked position is a
      `ValueError` naming the field; `"mask"`: such a sample is masked for that field only.

    At least one of `omega` and `quat` must be given. **Fields:** `ts` `(K, n)`, `omega`,
    `quat`, `sigma_omega`, `sigma_quat` (broadcast, `None` where not observed), `mask`,
    and the per-field masks `mask_omega`, `mask_quat` `(K, n)` used by the loss. Masked
    samples are stored as zeros / the identity quaternion.
    """

    ts: Float[Array, "K n"]
    omega: Float[Array, "K n 3"] | None
    quat: Float[Array, "K n 4"] | None
    sigma_omega: Float[Array, "K n 3"] | None
    sigma_quat: Float[Array, "K n"] | None
    mask: Bool[Array, "K n"]
    mask_omega: Bool[Array, "K n"]
    mask_quat: Bool[Array, "K n"]

    def __init__(
        self,
        ts: Float[ArrayLike, "*K n"],
        omega: Float[ArrayLike, "K n 3"] | None = None,
        quat: Float[ArrayLike, "K n 4"] | None = None,
        sigma_omega: Float[ArrayLike, "..."] | None = None,
        sigma_quat: Float[ArrayLike, "..."] | None = None,
        mask: Bool[ArrayLike, "K n"] | None = None,
        *,
        euler: Float[ArrayLike, "K n 3"] | None = None,
        seq: str = "ZXZ",
        degrees: bool = False,
        nan_policy: str = "raise",
        normalize_quat: bool = False,
    ):
        if euler is not None:
            if quat is not None:
                raise ValueError("Give the attitude as `quat` or as `euler`, not both.")
            angles = _as_np(euler, "euler")
            if angles.ndim != 3 or angles.shape[-1] != 3:
                raise ValueError(f"`euler` must have shape (K, n, 3), got {angles.shape}.")
            if degrees:
                angles = np.radians(angles)
            quat = np.asarray(rotation.euler_to_quat(jnp.asarray(angles), seq))
        if omega is None and quat is None:
            raise ValueError("Give at least one of `omega` and `quat` (or `euler`).")
        if nan_policy not in ("raise", "mask"):
            raise ValueError(f"`nan_policy` must be 'raise' or 'mask', got {nan_policy!r}.")
        first = omega if omega is not None else quat
        first_name = "omega" if omega is not None else "quat"
        first = _as_np(first, first_name)
        if first.ndim != 3:
            raise ValueError(f"`{first_name}` must have shape (K, n, …), got {first.shape}.")
        K, n = first.shape[:2]
        t = _as_np(ts, "ts")
        if t.ndim == 1:
            t = np.broadcast_to(t, (K, n)) if t.shape == (n,) else t
        if t.shape != (K, n):
            raise ValueError(f"`ts` must have shape ({n},) or ({K}, {n}), got {t.shape}.")
        m = np.ones((K, n), bool) if mask is None else np.asarray(mask)
        if m.shape != (K, n) or m.dtype != bool:
            raise ValueError(f"`mask` must be a boolean array of shape ({K}, {n}).")

        def field(x, name, width):
            if x is None:
                return None, np.zeros((K, n), bool)
            a = _as_np(x, name)
            if a.shape != (K, n, width):
                raise ValueError(f"`{name}` must have shape ({K}, {n}, {width}), got {a.shape}.")
            finite = np.all(np.isfinite(a), axis=-1)
            if nan_policy == "raise" and np.any(m & ~finite):
                k, i = np.argwhere(m & ~finite)[0]
                raise ValueError(
                    f"`{name}` has a non-finite sample (trajectory {k}, sample {i}); mask it "
                    "or pass `nan_policy='mask'`."
                )
            fm = m & finite
            return np.where(fm[..., None], a, 0.0), fm

        w, m_w = field(omega, "omega", 3)
        q, m_q = field(quat, "quat", 4)
        if q is not None:
            norm = np.linalg.norm(q, axis=-1)
            bad = m_q & ((norm == 0) | ((not normalize_quat) & (np.abs(norm - 1) > _UNIT_TOL)))
            if np.any(bad):
                k, i = np.argwhere(bad)[0]
                raise ValueError(
                    f"`quat` is not a unit quaternion at trajectory {k}, sample {i} "
                    f"(norm {norm[k, i]:.6g}); pass `normalize_quat=True` to renormalise."
                )
            ident = np.array([1.0, 0.0, 0.0, 0.0])
            q = np.where(m_q[..., None], q / np.where(m_q, norm, 1.0)[..., None], ident)
        valid = m_w | m_q
        t = np.stack([_fill_times(t[k], valid[k], k) for k in range(K)])
        self.ts = jnp.asarray(t)
        self.omega = None if w is None else jnp.asarray(w)
        self.quat = None if q is None else jnp.asarray(q)
        self.sigma_omega = (
            None if w is None else jnp.asarray(_sigma(sigma_omega, (K, n, 3), "sigma_omega"))
        )
        self.sigma_quat = (
            None if q is None else jnp.asarray(_sigma(sigma_quat, (K, n), "sigma_quat"))
        )
        self.mask = jnp.asarray(m)
        self.mask_omega = jnp.asarray(m_w)
        self.mask_quat = jnp.asarray(m_q)

    @property
    def num_trajectories(self) -> int:
        """K, the number of trajectories."""
        return self.ts.shape[0]

    @classmethod
    def from_file(
        cls,
        path: str | pathlib.Path,
        *,
        sigma_omega: Float[ArrayLike, "..."] | None = None,
        sigma_quat: Float[ArrayLike, "..."] | None = None,
        trajectories: int | None = None,
        seq: str = "ZXZ",
        normalize_quat: bool = False,
    ) -> "Observations":
        """Observations read from a file, chosen by its suffix:

        - `.npz`: arrays `ts` `(n,)` or `(K, n)`, `omega` `(K, n, 3)`, `quat` `(K, n, 4)` or
          `euler` `(K, n, 3)` of the sequence `seq` (or of the file's own `seq` array), and
          optionally `sigma_omega`, `sigma_quat`, `mask`; any other array is a `ValueError`;
        - `.csv`: a header naming a `t` column and `wx, wy, wz` and/or `qw, qx, qy, qz`,
          optionally a `trajectory` column (one trajectory per value; trajectories of
          different lengths are padded and masked); other columns (pandas' unnamed index
          column, say) are ignored;
        - anything else xarray opens (a sweep store, a netCDF file) with `omega` and/or
          `quat` over `trajectory` (or `sampled_trajectory`) and `time`; only the
          successful trajectories where it has a `status`.

        `trajectories` keeps the first K. `sigma_omega` and `sigma_quat`, where given,
        override the file's (default 1). `normalize_quat` renormalises the quaternions
        (as `Observations` does): a file written to a few decimals holds quaternions whose
        norms miss 1 by more than the 1e-6 otherwise allowed. A missing file is a
        `FileNotFoundError`; a file
        that is none of these, or holds no usable record, a `ValueError` naming it.
        """
        fields, seq = read_fields(path, trajectories=trajectories, seq=seq)
        if sigma_omega is not None:
            fields["sigma_omega"] = sigma_omega
        if sigma_quat is not None:
            fields["sigma_quat"] = sigma_quat
        return cls(
            fields.pop("ts"),
            omega=fields.get("omega"),
            quat=fields.get("quat"),
            sigma_omega=fields.get("sigma_omega"),
            sigma_quat=fields.get("sigma_quat"),
            mask=fields.get("mask"),
            euler=fields.get("euler"),
            seq=seq,
            normalize_quat=normalize_quat,
        )
