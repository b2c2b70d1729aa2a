"""The Lagrange top under a non-stationary restoring moment `k = ε K(τ) sin ψ`: its first
and second approximations, with the Gauss–Legendre quadratures of `K`."""

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import as_float_array
from .._program.xla import filter_jit
from ._helpers import check_times, safe_div

# Default Gauss–Legendre order of the restoring-moment quadratures: exact for polynomial K
# of degree ≤ 2·32 − 1 = 63 and converged to rounding for K analytic near [0, τ] with τ = O(1).
_GL_ORDER = 32

_Times = Float[Array, " n"]
_TimesLike = Float[ArrayLike, " n"]


# ---------------------------------------------------------------------------------------
# Lagrange top under a non-stationary restoring moment (Zinkevich & Kozachenko (2008);
# docs/physics.md#restoring-moment)
# ---------------------------------------------------------------------------------------


def _check_quad_order(order: int) -> None:
    if not isinstance(order, int) or isinstance(order, bool) or order < 1:
        raise ValueError(f"`quad_order` must be a positive int, got {order!r}.")


def _checked(C: Array, r0: Array) -> tuple[Array, Array]:
    """`C` and `r0` with their runtime checks: both approximations divide by `C r0`."""
    C = eqx.error_if(C, ~(C > 0), "`C` must be positive.")
    r0 = eqx.error_if(r0, r0 == 0, "`r0` must be non-zero: the approximations expand in 1/r0.")
    return C, r0


def _gl_rule(order: int, dtype) -> tuple[Array, Array]:
    x, w = np.polynomial.legendre.leggauss(order)
    return jnp.asarray(x, dtype=dtype), jnp.asarray(w, dtype=dtype)


def _integral_0_to(f: Callable[[Array], Array], upper: Array, x: Array, w: Array) -> Array:
    """`∫₀^upper f(s) ds` for every element of `upper` (Gauss–Legendre, nodes on a new axis)."""
    expand = (1,) * upper.ndim
    s = 0.5 * upper[..., None] * (x.reshape(expand + x.shape) + 1.0)
    return jnp.sum(w.reshape(expand + w.shape) * f(s), axis=-1) * upper * 0.5


def _call_K(K: Callable, s: Array) -> Array:
    out = jnp.asarray(K(s))
    if out.shape != s.shape:
        out = jnp.broadcast_to(out, s.shape)
    return out.astype(s.dtype)


def _psi_first(psi0: Array, F1: Array) -> Array:
    """ψ with `tan(ψ/2) = tan(ψ0/2) exp(F1)`, on the 2π branch of ψ0.

    docs/physics.md#first-approximation."""
    j = jnp.round(psi0 / (2.0 * jnp.pi))
    psr = psi0 - 2.0 * jnp.pi * j  # in [−π, π]
    half = 0.5 * psr
    return 2.0 * jnp.arctan2(jnp.sin(half) * jnp.exp(F1), jnp.cos(half)) + 2.0 * jnp.pi * j


def _scalars(**kw) -> dict[str, Array]:
    out = {}
    for name, v in kw.items():
        a = as_float_array(v, name)
        if a.ndim != 0:
            raise ValueError(f"`{name}` must be a scalar, got shape {tuple(a.shape)}.")
        out[name] = a
    return out


def lagrange_top_first_approximation(
    ts: _TimesLike,
    *,
    A: float,
    C: float,
    r0: float,
    psi0: float,
    theta0: float,
    eps: float,
    K: Callable[[Array], Array],
    M3: float = 0.0,
    quad_order: int = _GL_ORDER,
) -> tuple[_Times, _Times, _Times]:
    """First approximation of a Lagrange top under `k(τ, ψ) = ε K(τ) sin ψ`.

    Zinkevich & Kozachenko (2008), the averaged system in the first approximation
    (docs/physics.md#first-approximation): with the full equations (their eq. (1))
    `A p' + (C − A) q r = k sinθ cosφ`, `A q' + (A − C) p r = −k sinθ sinφ`,
    `C r' = M3` (perturbing `M1 = M2 = 0`; constant body-fixed ones average out at this
    order) and slow time `τ = ε t`,

        θ = θ0,   r = r0 + M3 t / C,
        tan(ψ/2) = tan(ψ0/2) · exp(F1(τ)),   F1(τ) = (C r0)⁻¹ ∫₀^τ K(s) ds,

    i.e. the averaged gyroscopic precession `ψ' = k / (C r0)` (for the heavy top, `k = mgl`,
    the slow precession `mgl / (C r)`). ψ stays on the 2π branch of `psi0`. Valid for
    `√(p² + q²) ≪ r`, `C r² ≫ k`, `|M3| ≪ k`, over `t = O(1/ε)`, with errors `O(ε)` (the
    nutation, of amplitude `~ A k / (C r0)²`, is averaged out).

    `F1` is computed by Gauss–Legendre quadrature of order `quad_order` on `[0, τ]`,
    exact for polynomial `K` of degree ≤ `2 quad_order − 1` and accurate to rounding for
    `K` analytic in a neighbourhood of `[0, τ]` with `τ = O(1)`.

    **Arguments:**

    - `ts`: times `(n,)`, `t = 0` at the initial condition.
    - `A`, `C`: equatorial and axial moments of inertia about the fixed point (`A` is
        unused at this order; it is taken for symmetry with the second approximation).
    - `r0`: initial axial spin `r(0)` (non-zero).
    - `psi0`, `theta0`: initial precession and nutation angles (ZXZ,
        docs/physics.md#euler-angles).
    - `eps`: the small parameter ε of `τ = ε t` and `k = ε K(τ) sin ψ`.
    - `K`: `K(τ)`, a JAX-traceable function called with an array of slow times and acting
        elementwise. It is a static argument of an internal `jit`: pass the same function
        object to reuse the compilation.
    - `M3`: constant axial perturbing moment (physical units, `M3 = ε² M3*` of Zinkevich &
        Kozachenko (2008), eq. (3)).
    - `quad_order`: Gauss–Legendre order of the quadrature.

    **Returns:**

    `(psi, theta, r)`, each of shape `(n,)`.

    **Raises:** `ValueError` for a malformed argument; `equinox.EquinoxRuntimeError` (at run
    time, also under `jit` and `vmap`) for `C ≤ 0` or `r0 = 0`.
    """
    ts = check_times(ts)
    s = _scalars(A=A, C=C, r0=r0, psi0=psi0, theta0=theta0, eps=eps, M3=M3)
    _check_quad_order(quad_order)
    return _first_impl(
        ts, s["C"], s["r0"], s["psi0"], s["theta0"], s["eps"], s["M3"], K, quad_order
    )


@filter_jit
def _first_impl(ts, C, r0, psi0, theta0, eps, M3, K, quad_order):
    C, r0 = _checked(C, r0)
    x, w = _gl_rule(quad_order, ts.dtype)
    tau = eps * ts
    F1 = _integral_0_to(lambda u: _call_K(K, u), tau, x, w) / (C * r0)
    psi = _psi_first(psi0, F1)
    theta = jnp.full_like(ts, theta0)
    r = r0 + M3 * ts / C
    return psi, theta, r


def lagrange_top_second_approximation(
    ts: _TimesLike,
    *,
    A: float,
    C: float,
    r0: float,
    psi0: float,
    theta0: float,
    eps: float,
    K: Callable[[Array], Array],
    M3: float = 0.0,
    phi0: float = 0.0,
    p0: float | None = None,
    q0: float | None = None,
    quad_order: int = _GL_ORDER,
) -> tuple[_Times, _Times, _Times]:
    """Second approximation of the Lagrange top of `lagrange_top_first_approximation`.

    docs/physics.md#second-approximation: the formulas of Zinkevich & Kozachenko (2008)
    that follow their eq. (5), re-derived and corrected (the printed forms fail the initial
    conditions at O(ε) and have sign and factor slips; see below). Errors `O(ε²)` over
    `t = O(1/ε)`.

    Mean motion (guiding centre: `L = A e × ė + C r e`, `dL/dt = N`, solved for ė to
    second order; it reproduces the paper's `g(τ)`):

        dψ̄/dτ = K sinψ̄ / (C r0) + ε A cosθ0 K² sin²ψ̄ / (C r0)³ − K sinψ̄ M3 τ / (ε C² r0²),
        θ̄ = θ̄0 + A sinθ̄0 (k(τ) − k(0)) / (C r0)²,   k = ε K(τ) sin ψ̄,

    the first line solved as `ψ̄ = ψ1 + sinψ1(τ) ∫₀^τ g(s) / sinψ1(s) ds` (`ψ1`: the first
    approximation from `ψ̄0`, `g` the two correction terms; the paper's `exp(∓F)` factors
    are `sinψ1(0) / sinψ1(τ)` in closed form). The paper's two θ integrals
    `∫ ∂K/∂τ sinψ1` and `∫ K² sin2ψ1` combine, with the correct factor `ε/2` on the second
    (printed `1/4`), into the closed form above.

    Fast nutation (the paper's S1, S2, with S1's sign corrected):

        ψ = ψ̄ − (A / (C r0 sinθ0)) e^{F/2} [â0 cos χ + b̂0 sin χ],
        θ = θ̄ + (A / (C r0)) e^{F/2} [â0 sin χ − b̂0 cos χ],
        χ = α − G = φ0 + C r0 t / A + M3 t² / (2A) − 2 cosθ0 (ψ1 − ψ̄0),
        e^{F} = sinψ̄0 / sinψ1(τ),
        â0 = p0 − (k0 / (C r0)) sinθ0 sinφ0,   b̂0 = −q0 + (k0 / (C r0)) sinθ0 cosφ0,

    (`ε a`, `ε b` of the paper at `t = 0`, `k0 = ε K(0) sin ψ0`), and the mean initial values
    `ψ̄0 = ψ0 − S1(0)`, `θ̄0 = θ0 − S2(0)`, so that `ψ(0) = ψ0`, `θ(0) = θ0` exactly.
    Perturbing moments `M1 = M2 = 0`.

    **Arguments:** as `lagrange_top_first_approximation`, plus the initial proper-rotation
    angle `phi0` and body rates `p0`, `q0` (default: the steady-precession values
    `p0 = ψ'0 sinθ0 sinφ0`, `q0 = ψ'0 sinθ0 cosφ0`, `ψ'0 = k0 / (C r0)`, for which the
    nutation vanishes to this order). `A` is used here.

    **Returns:**

    `(psi, theta, r)`, each of shape `(n,)`; `r = r0 + M3 t / C` (exact).

    **Raises:** as the first approximation, and also for `A ≤ 0`, `eps = 0` (the mean
    motion's `M3` term is in `τ / ε`) and `theta0` a multiple of π (to rounding: ψ is
    undefined with the body's axis on the vertical).
    """
    ts = check_times(ts)
    s = _scalars(A=A, C=C, r0=r0, psi0=psi0, theta0=theta0, eps=eps, M3=M3, phi0=phi0)
    p0 = None if p0 is None else _scalars(p0=p0)["p0"]
    q0 = None if q0 is None else _scalars(q0=q0)["q0"]
    _check_quad_order(quad_order)
    return _second_impl(
        ts,
        s["A"],
        s["C"],
        s["r0"],
        s["psi0"],
        s["theta0"],
        s["eps"],
        s["M3"],
        s["phi0"],
        p0,
        q0,
        K,
        quad_order,
    )


@filter_jit
def _second_impl(ts, A_, C_, r0_, ps0, th0, eps_, M3_, ph0, p0, q0, K, quad_order):
    C_, r0_ = _checked(C_, r0_)
    A_ = eqx.error_if(A_, ~(A_ > 0), "`A` must be positive.")
    eps_ = eqx.error_if(eps_, eps_ == 0, "`eps` must be non-zero: slow time is τ = ε t.")
    # θ0 = kπ: the line of nodes, so ψ, is undefined (the nutation's 1/sinθ0); in floating
    # point sin(π) is a rounding error, not 0.
    vertical = jnp.abs(jnp.sin(th0)) <= jnp.finfo(th0.dtype).eps
    th0 = eqx.error_if(th0, vertical, "`theta0` must not be a multiple of π: ψ is undefined there.")
    x, w = _gl_rule(quad_order, ts.dtype)
    Kf = lambda u: _call_K(K, u)  # noqa: E731
    Cr = C_ * r0_
    zero = jnp.zeros((), dtype=ts.dtype)

    k0 = eps_ * Kf(zero) * jnp.sin(ps0)
    rate0 = k0 / Cr
    p0_ = rate0 * jnp.sin(th0) * jnp.sin(ph0) if p0 is None else p0
    q0_ = rate0 * jnp.sin(th0) * jnp.cos(ph0) if q0 is None else q0
    a0 = p0_ - rate0 * jnp.sin(th0) * jnp.sin(ph0)
    b0 = -q0_ + rate0 * jnp.sin(th0) * jnp.cos(ph0)
    amp = A_ / Cr
    S1_0 = -amp / jnp.sin(th0) * (a0 * jnp.cos(ph0) + b0 * jnp.sin(ph0))
    S2_0 = amp * (a0 * jnp.sin(ph0) - b0 * jnp.cos(ph0))
    psib0 = ps0 - S1_0
    thb0 = th0 - S2_0

    def psi1(tau):
        return _psi_first(psib0, _integral_0_to(Kf, tau, x, w) / Cr)

    def g_over_sin(tau):  # g(τ) / sinψ1(τ), the integrand of the mean-ψ correction
        Kt = Kf(tau)
        return eps_ * A_ * jnp.cos(th0) * Kt**2 * jnp.sin(psi1(tau)) / Cr**3 - Kt * M3_ * tau / (
            eps_ * C_ * Cr * r0_
        )

    tau = eps_ * ts
    ps1 = psi1(tau)
    sin1 = jnp.sin(ps1)
    psibar = ps1 + sin1 * _integral_0_to(g_over_sin, tau, x, w)
    kbar = eps_ * Kf(tau) * jnp.sin(ps1)
    thbar = thb0 + A_ * jnp.sin(thb0) * (kbar - eps_ * Kf(zero) * jnp.sin(psib0)) / Cr**2

    sinb0 = jnp.sin(psib0)
    ratio = safe_div(sinb0, sin1)
    half_F = jnp.where(sinb0 == 0, 1.0, jnp.sqrt(jnp.abs(ratio)))  # e^{F/2}
    chi = ph0 + Cr * ts / A_ + M3_ * ts**2 / (2.0 * A_) - 2.0 * jnp.cos(th0) * (ps1 - psib0)
    S1 = -amp / jnp.sin(th0) * half_F * (a0 * jnp.cos(chi) + b0 * jnp.sin(chi))
    S2 = amp * half_F * (a0 * jnp.sin(chi) - b0 * jnp.cos(chi))
    r = r0_ + M3_ * ts / C_
    return psibar + S1, thbar + S2, r
