"""The integrable gravity-gradient case `A = B = m C`: its first integrals, the quartic of
the nutation and the nutation's half period by quadrature."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._checks import as_float_array, check_trailing
from .._custom_types import Scalar, ScalarLike, VectorLike

# ---------------------------------------------------------------------------------------
# gravity gradient, integrable case A = B = m C (Shinibaev et al. (2013);
# docs/physics.md#the-integrable-case)
# ---------------------------------------------------------------------------------------


def gg_integrable_case_integrals(
    A: ScalarLike, C: ScalarLike, eps: ScalarLike, omega: VectorLike, gamma: VectorLike
) -> tuple[Scalar, Scalar, Scalar, Scalar]:
    """First integrals of the integrable gravity-gradient case `A = B = m C`.

    Shinibaev et al. (2013), eqs. (7), (8), (10), (13), collected as (14)
    (docs/physics.md#the-integrable-case), `n = (1 − m)/m = (C − A)/A`:
    `C1 = p² + q² + ε n γ''²`, `C2 = γ p + γ' q + r (n + 1) γ''`, `r`, `|γ|²`.

    **Arguments:** `A` (= B), `C`, `eps` (ε = 3μ/R³), `(*batch)`; body angular velocity
    `omega = (p, q, r)` and body components `gamma = (γ, γ', γ'')` of the direction to the
    attracting centre, `(*batch, 3)`.

    **Returns:** `(C1, C2, r, |γ|²)`, each `(*batch)`.
    """
    A = as_float_array(A, "A")
    C = as_float_array(C, "C")
    eps = as_float_array(eps, "eps")
    omega = check_trailing(omega, (3,), "omega")
    gamma = check_trailing(gamma, (3,), "gamma")
    p, q, r = jnp.moveaxis(omega, -1, 0)
    g1, g2, g3 = jnp.moveaxis(gamma, -1, 0)
    n = (C - A) / A
    C1 = p * p + q * q + eps * n * g3 * g3
    C2 = g1 * p + g2 * q + r * (n + 1.0) * g3
    return C1, C2, r, g1 * g1 + g2 * g2 + g3 * g3


def gg_nutation_quartic(
    A: float, C: float, eps: float, omega0: ArrayLike, gamma0: ArrayLike
) -> np.ndarray:
    """Coefficients of the quartic `Q(u) = (du/dt)²`, `u = γ''`, of the nutation quadrature.

    Shinibaev et al. (2013), eq. (19); docs/physics.md#nutation-quadrature.
    From `r = r0`, `p² + q² = C1 − ε n u²`, `γ p + γ' q = C2 − r0 (n + 1) u`,
    `γ² + γ'² = 1 − u²`, Poisson `u' = q γ − p γ'` and the identity
    `(pγ + qγ')² + (qγ − pγ')² = (p² + q²)(γ² + γ'²)`:

        Q(u) = (C1 − ε n u²)(1 − u²) − (C2 − r0 (n + 1) u)²
             = a0 u⁴ + a2 u² + a3 u + a4,
        a0 = ε n,  a2 = −(ε n + C1 + r0² (n + 1)²),  a3 = 2 C2 r0 (n + 1),  a4 = C1 − C2²,

    exactly the coefficients of Shinibaev et al. (2013), eq. (19).

    **Arguments:** moments `A` (= B) and `C`, `eps` = ε, initial `omega0 = (p0, q0, r0)` and
    unit `gamma0 = (γ0, γ'0, γ''0)` (shape `(3,)` each).

    **Returns:** `[a0, 0, a2, a3, a4]` (highest power first, as `np.polyval`/`np.roots`).
    """
    A, C, eps, omega0, gamma0 = _gg_inputs(A, C, eps, omega0, gamma0)
    p0, q0, r0 = omega0
    g1, g2, g3 = gamma0
    n = (C - A) / A
    C1 = p0 * p0 + q0 * q0 + eps * n * g3 * g3
    C2 = g1 * p0 + g2 * q0 + r0 * (n + 1.0) * g3
    return np.array(
        [
            eps * n,
            0.0,
            -(eps * n + C1 + r0 * r0 * (n + 1.0) ** 2),
            2.0 * C2 * r0 * (n + 1.0),
            C1 - C2 * C2,
        ]
    )


def _gg_inputs(A, C, eps, omega0, gamma0):
    A, C, eps = float(A), float(C), float(eps)
    if not A > 0:
        raise ValueError(f"`A` must be positive, got {A}.")
    if not C > 0:
        raise ValueError(f"`C` must be positive, got {C}.")
    omega0 = np.asarray(omega0, dtype=float)
    gamma0 = np.asarray(gamma0, dtype=float)
    if omega0.shape != (3,):
        raise ValueError(f"`omega0` must have shape (3,), got {omega0.shape}.")
    if gamma0.shape != (3,):
        raise ValueError(f"`gamma0` must have shape (3,), got {gamma0.shape}.")
    if not np.all(np.isfinite(omega0)) or not np.all(np.isfinite(gamma0)):
        raise ValueError("`omega0` and `gamma0` must be finite.")
    if abs(np.dot(gamma0, gamma0) - 1.0) > 1e-9:
        raise ValueError(f"`gamma0` must be a unit vector, got |gamma0|² = {gamma0 @ gamma0}.")
    return A, C, eps, omega0, gamma0


def gg_nutation_half_period(
    A: float, C: float, eps: float, omega0: ArrayLike, gamma0: ArrayLike
) -> float:
    """Half period of the nutation γ''(t) in the integrable gravity-gradient case.

    Shinibaev et al. (2013), eq. (19) (docs/physics.md#nutation-quadrature): the time
    between successive turning points of `u = γ''` is `∫ du / √Q(u)` between the two
    adjacent real roots `u1 < u2` of the quartic `gg_nutation_quartic` that bracket `γ''0`
    (Q > 0 between them, inside [−1, 1]).
    Writing `Q = (u − u1)(u2 − u) g(u)` (g: Q divided by the two roots' factors, positive
    on [u1, u2]) and `u = mid + half · sin φ` removes both inverse-square-root endpoint
    singularities:

        T/2 = ∫_{−π/2}^{π/2} dφ / √g(mid + half sin φ),

    a smooth integrand, done by `scipy.integrate.quad` (relative tolerance 1e-13). The
    roots come from `np.roots`, polished by Newton steps. If `γ''0` is a double root
    (`u` constant: steady motion) the value is the limit of nearby motions: the
    small-oscillation value `π / √g(u*)` (`g = −Q''/2`) if the steady motion is stable,
    `inf` if it is unstable (nearby motions are asymptotic to it).

    **Arguments:** moments `A` (= B) and `C` (> 0), `eps` = ε = 3μ/R³, initial body rates
    `omega0 = (p0, q0, r0)` and unit `gamma0 = (γ0, γ'0, γ''0)`, shape `(3,)` each.

    **Returns:** the half period (a float).

    **Raises:** `ValueError` for bad arguments, or when no pair of real roots of the
    quartic brackets `γ''0` (which the equations of motion exclude).
    """
    coeffs = gg_nutation_quartic(A, C, eps, omega0, gamma0)
    u0 = float(np.asarray(gamma0, dtype=float)[2])
    scale = float(np.max(np.abs(coeffs)))
    if scale == 0:
        raise ValueError("the nutation quartic vanishes identically (`omega0` = 0, `eps` n = 0).")
    # Trim vanishing leading coefficients (ε n = 0: a quadratic, the torque-free body).
    poly = np.trim_zeros(np.where(np.abs(coeffs) <= 1e-300, 0.0, coeffs), "f")
    dpoly = np.polyder(poly)
    d2poly = np.polyder(dpoly)
    if abs(np.polyval(poly, u0)) <= 1e-12 * scale and abs(np.polyval(dpoly, u0)) <= 1e-8 * scale:
        # u0 is a double root: du/dt = d²u/dt² = 0, u stays constant (steady motion). The
        # limit of nearby motions: π/√g with g = −Q''/2 if stable, inf if unstable.
        curv = float(np.polyval(d2poly, u0))
        return float(np.pi / np.sqrt(-0.5 * curv)) if curv < 0 else math.inf
    roots = np.roots(poly)
    real = []
    for z in roots:
        if abs(z.imag) <= 1e-7 * max(1.0, abs(z)):
            x = z.real
            for _ in range(4):  # Newton polish, kept only while it helps
                d = np.polyval(dpoly, x)
                if d == 0:
                    break
                x_new = x - np.polyval(poly, x) / d
                if abs(np.polyval(poly, x_new)) >= abs(np.polyval(poly, x)):
                    break
                x = x_new
            real.append(x)
    real = sorted(real)
    tol = 1e-9 * max(1.0, abs(u0))
    interval = None
    for lo, hi in zip(real[:-1], real[1:]):
        positive = np.polyval(poly, 0.5 * (lo + hi)) > 0
        if lo - tol <= u0 <= hi + tol and hi > lo and positive:
            interval = (lo, hi)
            break
    if interval is None:
        raise ValueError(
            "no pair of real roots of the nutation quartic brackets `gamma0[2]`: "
            f"roots {np.sort_complex(roots)}, gamma0[2] = {u0}."
        )
    lo, hi = interval
    quotient, _ = np.polydiv(poly, np.poly([lo, hi]))
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def integrand(phi):
        return 1.0 / np.sqrt(-np.polyval(quotient, mid + half * np.sin(phi)))

    import scipy.integrate  # here, not at the top: it would slow `import rbdyn_jax`

    value, _ = scipy.integrate.quad(
        integrand, -0.5 * np.pi, 0.5 * np.pi, epsabs=0.0, epsrel=1e-13, limit=200
    )
    return float(value)
