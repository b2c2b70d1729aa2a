"""Non-JAX yardsticks for the performance benchmarks: the rigid-body equations solved per
trajectory (a) by a numba-compiled Dormand–Prince 5(4) integrator run in parallel over
trajectories with ``numba.prange`` and (b) by a plain scipy ``solve_ivp`` Python loop.

Independent of rbdyn_jax (imports neither it nor JAX). State ``y = (ω, q)``: body rates
ω (3,) and the scalar-first Hamilton quaternion q = [w, x, y, z] (4,) of the body→inertial
attitude, with

    J ω' = (J ω) × ω + M,    q' = ½ q ⊗ (0, ω),    γ = R(q)ᵀ e_z
         = (2(xz − wy), 2(yz + wx), w² − x² − y² + z²)   (body components of inertial z),

and the torque M of one of three models (params shared across the batch):

    "torque_free"       M = 0                          params: inertia
    "heavy_top"         M = weight · (γ × com)         params: inertia, weight, com
    "gravity_gradient"  M = eps · (γ × (J γ))          params: inertia, eps

q is not renormalised during the solve; outputs return q / |q|.

numba solver (same control as Hairer's DOPRI5 without PI stabilisation, and as scipy RK45):
Dormand–Prince 5(4) tableau with FSAL, local extrapolation (the 5th-order solution is
propagated), error estimate from the 5th/4th-order difference (Hairer's e coefficients),
error norm ``sqrt(mean_i (err_i / (atol + rtol·max(|y0_i|, |y1_i|)))²)`` over the 7
components, accept if ≤ 1, step factor ``min(10, max(0.2, 0.9·err^(−1/5)))`` (not > 1 right
after a rejection), initial step by Hairer's heuristic (as scipy's ``select_initial_step``),
output at ``ts`` by the 4th-order continuous extension (Shampine's interpolant, scipy RK45's
``P`` matrix), and the last step clipped to land exactly on ``ts[-1]``. No maximum step.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

MODELS = {"torque_free": 0, "heavy_top": 1, "gravity_gradient": 2}

# Dormand–Prince 5(4) tableau (c, a, b) and error coefficients e = b5 − b4 (Hairer's signs
# flipped, which does not matter under the norm).
C2, C3, C4, C5 = 1 / 5, 3 / 10, 4 / 5, 8 / 9  # unused: the equations are autonomous
A21 = 1 / 5
A31, A32 = 3 / 40, 9 / 40
A41, A42, A43 = 44 / 45, -56 / 15, 32 / 9
A51, A52, A53, A54 = 19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729
A61, A62, A63, A64, A65 = 9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656
B1, B3, B4, B5, B6 = 35 / 384, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84
E1, E3, E4, E5, E6, E7 = -71 / 57600, 71 / 16695, -71 / 1920, 17253 / 339200, -22 / 525, 1 / 40
# Dense output: y(t + θh) = y + h Σ_s K_s Σ_k P[s, k] θ^(k+1)  (scipy RK45.P, Shampine 1986).
P = np.array(
    [
        [1, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
        [0, 0, 0, 0],
        [0, 131558114200 / 32700410799, -68118460800 / 10900136933, 87487479700 / 32700410799],
        [0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
        [0, 127303824393 / 49829197408, -318862633887 / 49829197408, 701980252875 / 199316789632],
        [0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
        [0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423],
    ]
)

_KERNEL = None


def solver_functions(dtype, jit) -> dict:
    """The solver's functions for one trajectory in `dtype`, each decorated with `jit`
    (``numba.njit`` for the CPU solver of `numba_solve`; ``numba.cuda.jit(device=True)`` for
    the CUDA kernel of `_cuda.py`). Returns them by name; ``solve_one`` is the entry.

    Every constant is a ``dtype`` value held in the closure (numba freezes it as a typed
    constant) and the arithmetic holds no bare float literal, which numba would type float64:
    in float32 every operation is float32."""
    F = np.dtype(dtype).type
    zero, one, neg_one, half, neg_half, two = F(0), F(1), F(-1), F(0.5), F(-0.5), F(2)
    seven, ten, hundred, inf = F(7), F(10), F(100), F(np.inf)
    fifth, neg_fifth, safety, min_factor = F(0.2), F(-0.2), F(0.9), F(0.2)
    h_tiny, d_tiny, d2_tiny, h0_scale, h1_scale, h1_min = (
        F(1e-6),
        F(1e-5),
        F(1e-15),
        F(0.01),
        F(1e-3),
        F(1e-6),
    )
    a21 = F(A21)
    a31, a32 = F(A31), F(A32)
    a41, a42, a43 = F(A41), F(A42), F(A43)
    a51, a52, a53, a54 = F(A51), F(A52), F(A53), F(A54)
    a61, a62, a63, a64, a65 = F(A61), F(A62), F(A63), F(A64), F(A65)
    b1, b3, b4, b5, b6 = F(B1), F(B3), F(B4), F(B5), F(B6)
    e1, e3, e4, e5, e6, e7 = F(E1), F(E3), F(E4), F(E5), F(E6), F(E7)
    p0, p2, p3, p4, p5, p6 = (tuple(F(v) for v in P[s]) for s in (0, 2, 3, 4, 5, 6))
    zeros = (zero,) * 7

    @jit
    def rhs(code, y, prm):
        """Time derivative of the state 7-tuple y for model `code` (see MODELS)."""
        wx, wy, wz, qw, qx, qy, qz = y
        (
            J00,
            J01,
            J02,
            J10,
            J11,
            J12,
            J20,
            J21,
            J22,
            I00,
            I01,
            I02,
            I10,
            I11,
            I12,
            I20,
            I21,
            I22,
            c0,
            c1,
            c2,
            weight,
            eps,
        ) = prm
        hx = J00 * wx + J01 * wy + J02 * wz
        hy = J10 * wx + J11 * wy + J12 * wz
        hz = J20 * wx + J21 * wy + J22 * wz
        mx = hy * wz - hz * wy
        my = hz * wx - hx * wz
        mz = hx * wy - hy * wx
        if code != 0:
            gx = two * (qx * qz - qw * qy)
            gy = two * (qy * qz + qw * qx)
            gz = qw * qw - qx * qx - qy * qy + qz * qz
            if code == 1:
                ax, ay, az, s = c0, c1, c2, weight
            else:
                ax = J00 * gx + J01 * gy + J02 * gz
                ay = J10 * gx + J11 * gy + J12 * gz
                az = J20 * gx + J21 * gy + J22 * gz
                s = eps
            mx += s * (gy * az - gz * ay)
            my += s * (gz * ax - gx * az)
            mz += s * (gx * ay - gy * ax)
        return (
            I00 * mx + I01 * my + I02 * mz,
            I10 * mx + I11 * my + I12 * mz,
            I20 * mx + I21 * my + I22 * mz,
            neg_half * (qx * wx + qy * wy + qz * wz),
            half * (qw * wx + qy * wz - qz * wy),
            half * (qw * wy + qz * wx - qx * wz),
            half * (qw * wz + qx * wy - qy * wx),
        )

    @jit
    def dot(ks, cs, i):
        """Σ_s cs[s] ks[s][i] over the stage tuples ks."""
        acc = zero
        for s in range(len(cs)):
            acc += cs[s] * ks[s][i]
        return acc

    @jit
    def comb(y, h, ks, cs):
        """y + h Σ_s cs[s] ks[s], componentwise, as a 7-tuple."""
        return (
            y[0] + h * dot(ks, cs, 0),
            y[1] + h * dot(ks, cs, 1),
            y[2] + h * dot(ks, cs, 2),
            y[3] + h * dot(ks, cs, 3),
            y[4] + h * dot(ks, cs, 4),
            y[5] + h * dot(ks, cs, 5),
            y[6] + h * dot(ks, cs, 6),
        )

    @jit
    def poly(row, th):
        """Dense-output weight Σ_k row[k] θ^(k+1) (Horner)."""
        return th * (row[0] + th * (row[1] + th * (row[2] + th * row[3])))

    @jit
    def rms(v, y, z, rtol, atol):
        """sqrt(mean_i (v_i / (atol + rtol max(|y_i|, |z_i|)))²)."""
        acc = zero
        for i in range(7):
            r = v[i] / (atol + rtol * max(abs(y[i]), abs(z[i])))
            acc += r * r  # numba's x ** 2 is this product
        return F(math.sqrt(acc / seven))  # F(): the simulator's math.sqrt returns a float

    @jit
    def solve_one(code, prm, y0, ts, rtol, atol, max_steps, out):
        """DOPRI5 from ts[0] to ts[-1] for one state y0 (7,), writing out[j] = y(ts[j]);
        returns (steps, status). State and stages are 7-tuples (no allocation per step)."""
        y = (y0[0], y0[1], y0[2], y0[3], y0[4], y0[5], y0[6])
        t, tend, nout = ts[0], ts[ts.shape[0] - 1], ts.shape[0]
        for i in range(7):
            out[0, i] = y[i]
        k1 = rhs(code, y, prm)
        # Initial step (Hairer's heuristic, as scipy's select_initial_step with order 4).
        d0, d1 = rms(y, y, zeros, rtol, atol), rms(k1, y, zeros, rtol, atol)
        h0 = h_tiny if (d0 < d_tiny or d1 < d_tiny) else h0_scale * d0 / d1
        h0 = min(h0, tend - t)
        f1 = rhs(code, comb(y, h0, (k1,), (one,)), prm)
        d2 = rms(comb(f1, neg_one, (k1,), (one,)), y, zeros, rtol, atol) / h0
        if d1 <= d2_tiny and d2 <= d2_tiny:
            h1 = max(h1_min, h0 * h1_scale)
        else:
            h1 = (h0_scale / max(d1, d2)) ** fifth
        h = min(hundred * h0, h1, tend - t)

        steps, status, j, rejected = 0, 0, 1, False
        while j < nout:
            if steps >= max_steps:
                status = 1
                break
            # F(): under the simulator math.nextafter is float64's (a float32 t then gives 0)
            if h < ten * abs(F(math.nextafter(t, inf)) - t):
                status = 2
                break
            tnew = min(t + h, tend)
            h = tnew - t
            k2 = rhs(code, comb(y, h, (k1,), (a21,)), prm)
            k3 = rhs(code, comb(y, h, (k1, k2), (a31, a32)), prm)
            k4 = rhs(code, comb(y, h, (k1, k2, k3), (a41, a42, a43)), prm)
            k5 = rhs(code, comb(y, h, (k1, k2, k3, k4), (a51, a52, a53, a54)), prm)
            k6 = rhs(code, comb(y, h, (k1, k2, k3, k4, k5), (a61, a62, a63, a64, a65)), prm)
            ynew = comb(y, h, (k1, k3, k4, k5, k6), (b1, b3, b4, b5, b6))
            k7 = rhs(code, ynew, prm)  # FSAL stage
            e = comb(zeros, h, (k1, k3, k4, k5, k6, k7), (e1, e3, e4, e5, e6, e7))
            err = rms(e, y, ynew, rtol, atol)
            steps += 1
            if err <= one:
                factor = ten if err == zero else min(ten, safety * err**neg_fifth)
                if rejected:
                    factor = min(one, factor)
                ks = (k1, k2, k3, k4, k5, k6, k7)
                while j < nout and ts[j] <= tnew:
                    if ts[j] == tnew:
                        yo = ynew
                    else:
                        th = (ts[j] - t) / h
                        yo = comb(
                            y,
                            h,
                            ks,
                            (
                                poly(p0, th),
                                zero,
                                poly(p2, th),
                                poly(p3, th),
                                poly(p4, th),
                                poly(p5, th),
                                poly(p6, th),
                            ),
                        )
                    for i in range(7):
                        out[j, i] = yo[i]
                    j += 1
                t, y, k1 = tnew, ynew, k7
                h *= factor
                rejected = False
            else:
                h *= max(min_factor, safety * err**neg_fifth)
                rejected = True
        return steps, status

    return {"rhs": rhs, "dot": dot, "comb": comb, "poly": poly, "rms": rms, "solve_one": solve_one}


def _build_kernel():
    """Compile (once, lazily) the single-trajectory solver and the parallel batch driver;
    returns the batch driver."""
    import numba

    solve_one = solver_functions(np.float64, numba.njit(cache=False, fastmath=False))["solve_one"]

    @numba.njit(parallel=True, cache=False, fastmath=False)
    def solve_batch(code, prm, y0, ts, rtol, atol, max_steps, out, steps, status):
        for n in numba.prange(y0.shape[0]):
            steps[n], status[n] = solve_one(code, prm, y0[n], ts, rtol, atol, max_steps, out[n])

    return solve_batch


def _prepare(model, params, omega0, quat0, ts):
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; expected one of {sorted(MODELS)}")
    J = np.ascontiguousarray(params["inertia"], dtype=np.float64)
    weight = float(params.get("weight", 0.0))
    com = np.ascontiguousarray(params.get("com", np.zeros(3)), dtype=np.float64)
    eps = float(params.get("eps", 0.0))
    omega0 = np.atleast_2d(np.asarray(omega0, dtype=np.float64))
    quat0 = np.atleast_2d(np.asarray(quat0, dtype=np.float64))
    ts = np.ascontiguousarray(ts, dtype=np.float64)
    if J.shape != (3, 3) or com.shape != (3,):
        raise ValueError("`inertia` must be (3, 3) and `com` (3,).")
    if omega0.shape[1:] != (3,) or quat0.shape != (omega0.shape[0], 4):
        raise ValueError("`omega0` must be (N, 3) and `quat0` (N, 4).")
    if ts.ndim != 1 or ts.size < 2 or np.any(np.diff(ts) <= 0):
        raise ValueError("`ts` must be 1-D, strictly increasing, with at least 2 points.")
    y0 = np.ascontiguousarray(np.concatenate([omega0, quat0], axis=1))
    return MODELS[model], J, weight, com, eps, y0, ts


def _split(ys: np.ndarray, steps: np.ndarray, status: np.ndarray) -> dict:
    quat = ys[..., 3:] / np.linalg.norm(ys[..., 3:], axis=-1, keepdims=True)
    return {"omega": ys[..., :3].copy(), "quat": quat, "steps": steps, "status": status}


def numba_solve(
    model: str,
    params: dict,
    omega0: np.ndarray,
    quat0: np.ndarray,
    ts: np.ndarray,
    rtol: float,
    atol: float,
    max_steps: int = 100_000,
) -> dict:
    """Solve N trajectories with the numba DOPRI5 kernel, in parallel over trajectories.

    `omega0` (N, 3), `quat0` (N, 4) scalar-first, `ts` (n,) strictly increasing (the solve runs
    from ts[0] to ts[-1]). Returns {"omega": (N, n, 3), "quat": (N, n, 4) unit, "steps": (N,)
    accepted + rejected steps, "status": (N,) 0 ok, 1 max_steps reached, 2 step too small};
    outputs not reached are NaN. Compiles on first call (see `warmup`).
    """
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = _build_kernel()
    code, J, weight, com, eps, y0, ts = _prepare(model, params, omega0, quat0, ts)
    N = y0.shape[0]
    out = np.full((N, ts.size, 7), np.nan)
    steps = np.zeros(N, dtype=np.int64)
    status = np.zeros(N, dtype=np.int64)
    # Parameters as a flat float tuple (J row-major, J⁻¹ row-major, com, weight, eps): scalars,
    # not arrays, inside the kernel, so the 7 right-hand-side calls per step stay in registers.
    prm = tuple(float(v) for v in (*J.ravel(), *np.linalg.inv(J).ravel(), *com, weight, eps))
    _KERNEL(code, prm, y0, ts, float(rtol), float(atol), int(max_steps), out, steps, status)
    return _split(out, steps, status)


def warmup() -> None:
    """Compile the numba kernel and run it once for each of the three models on a tiny problem."""
    params = {
        "inertia": np.diag([1.0, 2.0, 3.0]),
        "weight": 1.0,
        "com": np.array([0.0, 0.0, 0.1]),
        "eps": 0.1,
    }
    for model in MODELS:
        numba_solve(
            model,
            params,
            np.array([[0.1, 0.2, 1.0]]),
            np.array([[1.0, 0.0, 0.0, 0.0]]),
            np.linspace(0.0, 1.0, 3),
            1e-6,
            1e-6,
        )


def _numpy_rhs(code, J, Jinv, weight, com, eps, xp=np):
    """f(t, y) of the 7-state (ω, q) in NumPy, or in any NumPy-like module `xp` (`jax.numpy`
    for `compile.py`'s bare-diffrax yardstick)."""

    def f(t, y):
        w, (qw, qx, qy, qz) = y[:3], y[3:]
        m = xp.cross(J @ w, w)
        if code != 0:
            g = xp.stack(
                [
                    2 * (qx * qz - qw * qy),
                    2 * (qy * qz + qw * qx),
                    qw * qw - qx * qx - qy * qy + qz * qz,
                ]
            )
            m = m + (weight * xp.cross(g, com) if code == 1 else eps * xp.cross(g, J @ g))
        wx, wy, wz = w
        return xp.concatenate(
            [
                Jinv @ m,
                xp.stack(
                    [
                        -0.5 * (qx * wx + qy * wy + qz * wz),
                        0.5 * (qw * wx + qy * wz - qz * wy),
                        0.5 * (qw * wy + qz * wx - qx * wz),
                        0.5 * (qw * wz + qx * wy - qy * wx),
                    ]
                ),
            ]
        )

    return f


_STAGES = {"RK45": 6, "DOP853": 12, "RK23": 3}


def scipy_solve(
    model: str, params: dict, omega0, quat0, ts, rtol, atol, method: str = "DOP853"
) -> dict:
    """Solve N trajectories one `solve_ivp` call at a time (NumPy right-hand side).

    Same arguments and return layout as `numba_solve`; "status" is 0 ok, 1 solver failure.
    "steps" is nfev // stages of `method` (6 for RK45, 12 for DOP853, 3 for RK23): it ignores
    the start-up evaluations and, for DOP853, counts the 3 extra evaluations per step used by
    its dense output at `ts`, so it overestimates DOP853's step count somewhat.
    """
    code, J, weight, com, eps, y0, ts = _prepare(model, params, omega0, quat0, ts)
    fun = _numpy_rhs(code, J, np.linalg.inv(J), weight, com, eps)
    N = y0.shape[0]
    out = np.full((N, ts.size, 7), np.nan)
    steps = np.zeros(N, dtype=np.int64)
    status = np.zeros(N, dtype=np.int64)
    for n in range(N):
        sol = solve_ivp(fun, (ts[0], ts[-1]), y0[n], method=method, t_eval=ts, rtol=rtol, atol=atol)
        out[n, : sol.y.shape[1]] = sol.y.T
        steps[n] = sol.nfev // _STAGES.get(method, 1)
        status[n] = 0 if sol.success else 1
    return _split(out, steps, status)
