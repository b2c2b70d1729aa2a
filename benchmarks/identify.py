"""Inertia identification: `rbdyn_jax.identify.fit` (Levenberg–Marquardt, forward-mode
Jacobian through the solver, one compiled program) vs a scipy baseline
(`scipy.optimize.least_squares` with finite-difference Jacobians over `solve_ivp`
integrations), side by side in one run on the same synthetic data.

Setting: a body with products of inertia, J = [[2, 0.1, −0.05], [0.1, 3, 0.08],
[−0.05, 0.08, 3.5]], under the known torque `UniformGravity(weight=2, com=(0, 0, 0.1))`
(which fixes the scale of J); K trajectories (default 3) with random initial rates
(|ω0| ≈ 1.2) and random attitudes, n samples (default 50) on t ∈ [0, 5]; ω and attitude
observed with σ_ω = σ_q = 1e-3 (attitude noise q ⊗ exp(σ_q ε), random quaternion sign).
The truth is integrated at rtol = atol = 1e-12 (DOP853); both fits integrate at
rtol = atol = 1e-10, float64 (JAX on its default backend, recorded in the JSON).

Both methods solve the same problem:
- free parameters: the log-Cholesky θ of the planar inertia J' (6; J' = L Lᵀ,
  J = tr(J') I − J', docs/physics.md#log-cholesky-parametrisation) and, per trajectory,
  ω0 (3) and a rotation-vector correction δ of the attitude, q0 = q0_guess ⊗ exp(δ) (3):
  6 + 6K parameters;
- whitened residuals [(ω_sim − ω_obs)/σ_ω ; rotvec(q_obs* ⊗ q_sim)/σ_q], cost ½ Σ r²;
- starting guess: J_guess = 1.1 · diag(J_true) (no products of inertia, moments 10 % off),
  ω0 and q0 the first observed samples, δ = 0.
rbdyn_jax: `fit` with its defaults (LM, 30 iterations, Tsit5). scipy: `least_squares`
(`--scipy-method`, default "trf"; `jac="2-point"`, default tolerances) whose residual
function runs one `solve_ivp` per trajectory (`--integrator`, default DOP853) on Euler's
equations J ω' = J ω × ω + M and q' = ½ q ⊗ (0, ω), written in plain Python/NumPy.
Same objective, checked: the NumPy log-Cholesky map against rbdyn_jax's, and the scipy
residual's cost at rbdyn's optimum against rbdyn's final cost (`checks` in the JSON).

Timed: the rbdyn fit's first call (includes compilation), then `--repeats` fits on fresh
noise draws of the same sizes (compiled; median), and one scipy fit on the first draw; then
the first rbdyn fit of the first draw in two new processes sharing a new directory for JAX's
persistent compilation cache: the first finds it empty (it compiles and stores the fit), the
second loads the fit from it (its traced and compiled program) instead of tracing and
compiling (`--no-cache-processes` skips them).
Reported per method: wall time, residual / Jacobian evaluations, final cost, max |J_fit −
J_true|, and that error in units of rbdyn's standard errors (Gauss–Newton covariance of the
same draw's rbdyn fit; max over the 6 distinct entries); the ratio of wall times
scipy / rbdyn. rbdyn's LM runs a fixed number of iterations (`--steps`, default 30 as
`identify.LevenbergMarquardt()`): its time scales with it, whatever iteration the cost
settled at (printed).

Run: `python benchmarks/identify.py [--trajectories 3] [--samples 50] [--seed 0]` — prints a
table and writes results/benchmarks/identify.json.
"""

import argparse
import json
import pathlib
import platform
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from rbdyn_jax import identify as idf  # noqa: E402

J_TRUE = np.array([[2.0, 0.1, -0.05], [0.1, 3.0, 0.08], [-0.05, 0.08, 3.5]])
WEIGHT, COM = 2.0, np.array([0.0, 0.0, 0.1])
T_END, SIGMA_W, SIGMA_Q = 5.0, 1e-3, 1e-3
TOL, TRUTH_TOL = 1e-10, 1e-12
UPPER = np.triu_indices(3)


# ----------------------------------------------------------------------------------------
# Synthetic data (shared by both methods).
# ----------------------------------------------------------------------------------------


def gravity():
    return rb.UniformGravity(weight=WEIGHT, com=jnp.asarray(COM))


def initial_states(K, seed):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(K, 3))
    w = 1.2 * w / np.linalg.norm(w, axis=1, keepdims=True)
    q = Rotation.random(K, rng=rng).as_quat(scalar_first=True)
    return w, q


def truth(K, ts, seed):
    """Noise-free records, integrated at rtol = atol = 1e-12 (DOP853 on the NumPy model
    below, which the cost check of `main` ties to rbdyn_jax's; no compilation here)."""
    w0, q0 = initial_states(K, seed)
    rhs = make_rhs(J_TRUE, [0])
    ws, qs = [], []
    for w, q in zip(w0, q0):
        sol = solve_ivp(
            rhs,
            (ts[0], ts[-1]),
            np.concatenate([w, q]),
            t_eval=ts,
            method="DOP853",
            rtol=TRUTH_TOL,
            atol=TRUTH_TOL,
        )
        ws.append(sol.y[:3].T)
        qs.append(sol.y[3:].T / np.linalg.norm(sol.y[3:], axis=0)[:, None])
    return np.stack(ws), np.stack(qs)


def noisy(omega, quat, seed):
    """Noisy records: ω + σ_ω ε, q ⊗ exp(σ_q ε), random quaternion sign."""
    rng = np.random.default_rng(seed)
    w = omega + SIGMA_W * rng.standard_normal(omega.shape)
    dq = Rotation.from_rotvec(SIGMA_Q * rng.standard_normal(omega.shape).reshape(-1, 3))
    q = np_quat_multiply(quat, dq.as_quat(scalar_first=True).reshape(quat.shape))
    q = np.where(rng.random(q.shape[:-1] + (1,)) < 0.5, -q, q)
    return w, q


# ----------------------------------------------------------------------------------------
# The scipy baseline: NumPy forward model, residuals, least_squares.
# ----------------------------------------------------------------------------------------


def np_from_log_cholesky(theta):
    """J = tr(J') I − J', J' = L Lᵀ, theta = (log L00, log L11, log L22, L10, L20, L21)."""
    l00, l11, l22, l10, l20, l21 = theta
    L = np.array([[np.exp(l00), 0.0, 0.0], [l10, np.exp(l11), 0.0], [l20, l21, np.exp(l22)]])
    Jp = L @ L.T
    return np.trace(Jp) * np.eye(3) - Jp


def np_to_log_cholesky(J):
    Jp = 0.5 * np.trace(J) * np.eye(3) - J
    L = np.linalg.cholesky(Jp)
    return np.array([np.log(L[0, 0]), np.log(L[1, 1]), np.log(L[2, 2]), L[1, 0], L[2, 0], L[2, 1]])


def np_quat_multiply(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def np_quat_from_rotvec(v):
    return (
        Rotation.from_rotvec(np.reshape(v, (-1, 3)))
        .as_quat(scalar_first=True)
        .reshape(np.shape(v)[:-1] + (4,))
    )


def np_quat_to_rotvec(q):
    """Rotation vector of q (normalised, taken with w ≥ 0), as `rotation.quat_to_rotvec`."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    w, u = q[..., 0], q[..., 1:]
    s = np.linalg.norm(u, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-12
    scale = np.where(small, 2.0 / w, angle / np.where(small, 1.0, s))
    return scale[..., None] * u


def make_rhs(J, counter):
    """Euler's equations J ω' = J ω × ω + M, M = mg γ × r_c (γ = R(q)ᵀ e_z), and
    q' = ½ q ⊗ (0, ω), in scalar Python (faster than small NumPy ops per call)."""
    (a, b, c), (d, e, f), (g, h, i) = J.tolist()
    (ia, ib, ic), (id_, ie, if_), (ig, ih, ii) = np.linalg.inv(J).tolist()
    rx, ry, rz = COM.tolist()
    mg = WEIGHT

    def rhs(t, y):
        counter[0] += 1
        p, q, r, qw, qx, qy, qz = y.tolist()
        hx, hy, hz = a * p + b * q + c * r, d * p + e * q + f * r, g * p + h * q + i * r
        gx, gy, gz = (
            2.0 * (qx * qz - qw * qy),
            2.0 * (qy * qz + qw * qx),
            qw * qw - qx * qx - qy * qy + qz * qz,
        )
        mx = hy * r - hz * q + mg * (gy * rz - gz * ry)
        my = hz * p - hx * r + mg * (gz * rx - gx * rz)
        mz = hx * q - hy * p + mg * (gx * ry - gy * rx)
        return [
            ia * mx + ib * my + ic * mz,
            id_ * mx + ie * my + if_ * mz,
            ig * mx + ih * my + ii * mz,
            -0.5 * (qx * p + qy * q + qz * r),
            0.5 * (qw * p + qy * r - qz * q),
            0.5 * (qw * q + qz * p - qx * r),
            0.5 * (qw * r + qx * q - qy * p),
        ]

    return rhs


def np_simulate(J, w0, q0, ts, integrator, counter):
    rhs = make_rhs(J, counter)
    ws, qs = [], []
    for w, q in zip(w0, q0):
        sol = solve_ivp(
            rhs,
            (ts[0], ts[-1]),
            np.concatenate([w, q]),
            t_eval=ts,
            method=integrator,
            rtol=TOL,
            atol=TOL,
        )
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed: {sol.message}")
        ws.append(sol.y[:3].T)
        qs.append(sol.y[3:].T)
    return np.stack(ws), np.stack(qs)


class ScipyProblem:
    """x = [θ (6), ω0 (K, 3), δ (K, 3)] → whitened residuals, same layout as
    `identify.residuals`: ω residuals of all samples, then attitude residuals."""

    def __init__(self, ts, w_obs, q_obs, q0_guess, integrator):
        self.ts, self.w_obs, self.q_obs, self.q0_guess = ts, w_obs, q_obs, q0_guess
        self.integrator = integrator
        self.K = w_obs.shape[0]
        self.calls, self.rhs_evals = 0, [0]

    def unpack(self, x):
        K = self.K
        J = np_from_log_cholesky(x[:6])
        w0 = x[6 : 6 + 3 * K].reshape(K, 3)
        q0 = np_quat_multiply(self.q0_guess, np_quat_from_rotvec(x[6 + 3 * K :].reshape(K, 3)))
        return J, w0, q0

    def __call__(self, x):
        self.calls += 1
        J, w0, q0 = self.unpack(x)
        w, q = np_simulate(J, w0, q0, self.ts, self.integrator, self.rhs_evals)
        dq = np_quat_multiply(self.q_obs * np.array([1.0, -1.0, -1.0, -1.0]), q)
        return np.concatenate(
            [((w - self.w_obs) / SIGMA_W).ravel(), (np_quat_to_rotvec(dq) / SIGMA_Q).ravel()]
        )


# ----------------------------------------------------------------------------------------
# Runs.
# ----------------------------------------------------------------------------------------


def j_guess():
    return 1.1 * np.diag(np.diag(J_TRUE))


def run_rbdyn(ts, w_obs, q_obs, steps):
    data = idf.Observations(ts, omega=w_obs, quat=q_obs, sigma_omega=SIGMA_W, sigma_quat=SIGMA_Q)
    model = rb.RigidBody(jnp.asarray(j_guess()), gravity())
    y0 = rb.State(jnp.asarray(w_obs[:, 0]), jnp.asarray(q_obs[:, 0]))
    t0 = time.perf_counter()
    res = jax.block_until_ready(
        idf.fit(
            model, data, y0=y0, rtol=TOL, atol=TOL, optimizer=idf.LevenbergMarquardt(steps=steps)
        )
    )
    wall = time.perf_counter() - t0
    hist = np.asarray(res.loss_history)
    final = float(res.loss)
    # LM iterations until the cost is within 1e-9 (relative) of its final value
    iters = int(np.argmax(hist <= final * (1 + 1e-9)))
    J = np.asarray(res.model.inertia)
    x = np.concatenate(
        [
            np.asarray(rb.inertia.to_log_cholesky(res.model.inertia)),
            np.asarray(res.y0.omega).ravel(),
            np.zeros(3 * w_obs.shape[0]),
        ]
    )
    return {
        "wall_s": wall,
        "residual_evals": steps + 1,
        "jacobian_evals": steps + 1,
        "iterations_to_final_cost": iters,
        "cost": final,
        "converged": res.converged,
        "J_fit": J,
        "stderr_J": np.asarray(res.stderr["inertia"]),
        "x": x,
        "q0_fit": np.asarray(res.y0.quat),
    }


def first_draw(K, n, seed):
    """The first draw's times and noisy records."""
    ts = np.linspace(0.0, T_END, n)
    omega, quat = truth(K, ts, seed)
    return ts, omega, quat, *noisy(omega, quat, seed + 1000)


def run_in_new_process(K, n, seed, steps, cache):
    """`run_rbdyn` on the first draw in a new process whose JAX persistent compilation cache
    is the directory `cache` (this script as `--child-cache`); its J_fit and stderr_J as
    arrays."""
    args = [
        sys.executable,
        __file__,
        "--child-cache",
        str(cache),
        "--trajectories",
        str(K),
        "--samples",
        str(n),
        "--seed",
        str(seed),
        "--steps",
        str(steps),
    ]
    proc = subprocess.run(args, capture_output=True, text=True, check=True)
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    return {**r, "J_fit": np.array(r["J_fit"]), "stderr_J": np.array(r["stderr_J"])}


def child(K, n, seed, steps, cache):
    """`run_in_new_process`'s side: the cache configured before JAX compiles anything."""
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    ts, _, _, w_obs, q_obs = first_draw(K, n, seed)
    r = run_rbdyn(ts, w_obs, q_obs, steps)
    print(
        json.dumps(
            {
                k: v.tolist() if isinstance(v, np.ndarray) else v
                for k, v in r.items()
                if k not in ("x", "q0_fit")
            }
        )
    )


def run_scipy(ts, w_obs, q_obs, method, integrator):
    K = w_obs.shape[0]
    prob = ScipyProblem(ts, w_obs, q_obs, q_obs[:, 0], integrator)
    x0 = np.concatenate([np_to_log_cholesky(j_guess()), w_obs[:, 0].ravel(), np.zeros(3 * K)])
    t0 = time.perf_counter()
    sol = least_squares(prob, x0, jac="2-point", method=method)
    wall = time.perf_counter() - t0
    return {
        "wall_s": wall,
        "residual_evals": prob.calls,
        "nfev": int(sol.nfev),
        "jacobian_evals": int(sol.njev) if sol.njev is not None else None,
        "rhs_evals": prob.rhs_evals[0],
        "cost": float(sol.cost),
        "converged": bool(sol.success),
        "status": int(sol.status),
        "J_fit": np_from_log_cholesky(sol.x[:6]),
        "x": sol.x,
        "prob": prob,
    }


def log_cholesky_check():
    """Max difference between the NumPy and rbdyn_jax log-Cholesky maps (both ways)."""
    theta = np_to_log_cholesky(J_TRUE) + 0.05 * np.random.default_rng(123).normal(size=6)
    J_rb = np.asarray(rb.inertia.from_log_cholesky(jnp.asarray(theta)))
    theta_rb = np.asarray(rb.inertia.to_log_cholesky(jnp.asarray(J_TRUE)))
    return float(
        max(
            np.max(np.abs(np_from_log_cholesky(theta) - J_rb)),
            np.max(np.abs(theta_rb - np_to_log_cholesky(J_TRUE))),
        )
    )


def summarise(name, r, stderr):
    err = np.abs(r["J_fit"] - J_TRUE)
    row = {k: v for k, v in r.items() if k not in ("J_fit", "stderr_J", "x", "prob", "q0_fit")}
    row.update(
        {
            "method": name,
            "max_abs_err_J": float(err.max()),
            "max_err_in_stderr": float(np.max((err / stderr)[UPPER])),
            "J_fit": r["J_fit"].tolist(),
        }
    )
    return row


def main(
    trajectories=3,
    samples=50,
    seed=0,
    repeats=3,
    steps=30,
    scipy_method="trf",
    integrator="DOP853",
    out="results/benchmarks/identify.json",
    cache_processes=True,
):
    K, n = trajectories, samples
    ts, omega, quat, w_obs, q_obs = first_draw(K, n, seed)
    checks = {"log_cholesky_max_diff": log_cholesky_check()}

    # rbdyn: first call (compiles) on draw 0, then compiled calls on fresh draws.
    first = run_rbdyn(ts, w_obs, q_obs, steps)
    stderr = first["stderr_J"]
    compiled = [run_rbdyn(ts, *noisy(omega, quat, seed + 1001 + i), steps) for i in range(repeats)]
    times = [c["wall_s"] for c in compiled]
    sp = run_scipy(ts, w_obs, q_obs, scipy_method, integrator)
    processes = []
    if cache_processes:
        with tempfile.TemporaryDirectory(prefix="rbdyn_identify_cache_") as cache:
            processes = [run_in_new_process(K, n, seed, steps, cache) for _ in range(2)]

    rows = [
        summarise("rbdyn fit (first call)", first, stderr),
        # accuracy of the first fresh draw (own stderr), median time over the draws
        summarise("rbdyn fit (compiled, fresh draw)", compiled[0], compiled[0]["stderr_J"]),
        summarise(f"scipy least_squares {scipy_method}", sp, stderr),
    ]
    rows[1]["wall_s"] = float(np.median(times))
    rows[1]["wall_s_all"] = times
    for name, r in zip(("empty", "warm"), processes):
        rows.append(summarise(f"rbdyn fit (new process, {name} cache)", r, stderr))
    for r in rows:
        r["time_ratio_scipy_over_this"] = sp["wall_s"] / r["wall_s"]
    # Same objective? The scipy residual at rbdyn's optimum (same draw) vs scipy's own.
    x_rb = first["x"].copy()
    dq = np_quat_multiply(q_obs[:, 0] * np.array([1.0, -1.0, -1.0, -1.0]), first["q0_fit"])
    x_rb[6 + 3 * K :] = np_quat_to_rotvec(dq).ravel()
    r_at = sp["prob"](x_rb)
    checks.update(
        {
            "scipy_cost_at_rbdyn_optimum": float(0.5 * r_at @ r_at),
            # the two residual functions agree where rbdyn stopped: the same objective
            "cost_rel_diff_at_rbdyn_optimum": float(
                abs(0.5 * r_at @ r_at - first["cost"]) / first["cost"]
            ),
            "max_abs_J_rbdyn_minus_scipy": float(np.max(np.abs(first["J_fit"] - sp["J_fit"]))),
            "max_J_rbdyn_minus_scipy_in_stderr": float(
                np.max((np.abs(first["J_fit"] - sp["J_fit"]) / stderr)[UPPER])
            ),
        }
    )
    ratios = {
        "scipy_over_rbdyn_compiled": sp["wall_s"] / rows[1]["wall_s"],
        "scipy_over_rbdyn_first_call": sp["wall_s"] / first["wall_s"],
    }
    if processes:
        ratios["scipy_over_rbdyn_warm_cache_process"] = sp["wall_s"] / processes[1]["wall_s"]

    head = (
        f"{'method':<38} {'wall s':>8} {'res/jac evals':>14} {'cost':>10} "
        f"{'max|ΔJ|':>9} {'/stderr':>8} {'scipy/this':>10}"
    )
    print(
        f"K = {K} trajectories × n = {n} samples, {6 + 6 * K} parameters, "
        f"{6 * K * n} residuals, seed {seed}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        ev = f"{r['residual_evals']}/{r['jacobian_evals'] or '-'}"
        print(
            f"{r['method']:<38} {r['wall_s']:>8.2f} {ev:>14} {r['cost']:>10.2f} "
            f"{r['max_abs_err_J']:>9.2e} {r['max_err_in_stderr']:>8.2f} "
            f"{r['time_ratio_scipy_over_this']:>9.1f}x"
        )
    print(
        f"scipy: {sp['nfev']} nfev + finite differences = {sp['residual_evals']} residual "
        f"calls, {sp['rhs_evals']} rhs evaluations; rbdyn: {steps} LM iterations, cost "
        f"final after {first['iterations_to_final_cost']}"
    )
    c = checks
    print(
        f"checks: scipy's cost at rbdyn's optimum {c['scipy_cost_at_rbdyn_optimum']:.4f} "
        f"(rel. diff {c['cost_rel_diff_at_rbdyn_optimum']:.1e}), "
        f"|J_rbdyn − J_scipy| {checks['max_abs_J_rbdyn_minus_scipy']:.1e} "
        f"({checks['max_J_rbdyn_minus_scipy_in_stderr']:.2f} stderr)"
    )

    meta = {
        "machine": platform.platform(),
        "devices": jax.device_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "scipy": version("scipy"),
        "trajectories": K,
        "samples": n,
        "t_end": T_END,
        "seed": seed,
        "repeats": repeats,
        "sigma_omega": SIGMA_W,
        "sigma_quat": SIGMA_Q,
        "rtol": TOL,
        "atol": TOL,
        "n_params": 6 + 6 * K,
        "n_residuals": 6 * K * n,
        "lm_steps": steps,
        "scipy_method": scipy_method,
        "integrator": integrator,
        "free": ["inertia (log-Cholesky)", "omega0", "attitude correction"],
        "J_true": J_TRUE.tolist(),
        "J_guess": j_guess().tolist(),
        "stderr_J": stderr.tolist(),
    }
    path = pathlib.Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({"meta": meta, "rows": rows, "ratios": ratios, "checks": checks}, indent=2)
    )
    print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectories", type=int, default=3)
    p.add_argument("--samples", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=3, help="compiled rbdyn fits (fresh draws)")
    p.add_argument("--steps", type=int, default=30, help="LM iterations of the rbdyn fit")
    p.add_argument("--scipy-method", default="trf", choices=["trf", "lm", "dogbox"])
    p.add_argument("--integrator", default="DOP853", choices=["DOP853", "RK45"])
    p.add_argument("--out", default="results/benchmarks/identify.json")
    p.add_argument(
        "--no-cache-processes",
        action="store_true",
        help="skip the first fits in new processes with the persistent cache",
    )
    p.add_argument("--child-cache", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child_cache:
        child(args.trajectories, args.samples, args.seed, args.steps, args.child_cache)
    else:
        main(
            args.trajectories,
            args.samples,
            args.seed,
            args.repeats,
            args.steps,
            args.scipy_method,
            args.integrator,
            args.out,
            not args.no_cache_processes,
        )
