"""Throughput of batched forward solves: rbdyn_jax `simulate_batch` vs a scipy `solve_ivp`
loop, side by side in one run, with the accuracy of each against the Jacobi elliptic
solution printed beside its speed.

Setting: torque-free asymmetric body (moments 1, 2, 3), random initial rates |ω| ≈ 1,
t ∈ [0, 20], 101 output times, rtol = atol = 1e-8, float64 (PHYSICS.md §4). rbdyn_jax uses
its default Tsit5; the scipy loop uses RK45 (Dormand–Prince, the same order 5(4)) on the
same equations written in NumPy, one `solve_ivp` call per trajectory.

Run: `python benchmarks/throughput.py [--sizes 1 10 100 1000]` — prints a table and writes
results/benchmarks/throughput.json.
"""

import argparse
import json
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import rbdyn_jax as rb  # noqa: E402

MOMENTS = np.array([1.0, 2.0, 3.0])
T_END, N_OUT, TOL = 20.0, 101, 1e-8


def initial_rates(n, seed=0):
    w = np.random.default_rng(seed).normal(size=(n, 3))
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def reference(w0, ts):
    return np.asarray(jax.vmap(lambda w: rb.analytic.torque_free_elliptic(MOMENTS, w, ts))(
        jnp.asarray(w0)))


def run_rbdyn(w0, ts, repeats):
    model = rb.RigidBody(jnp.diag(jnp.asarray(MOMENTS)))
    y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (len(w0), 1)))
    t0 = time.perf_counter()
    traj = jax.block_until_ready(rb.simulate_batch(model, y0s, ts, rtol=TOL, atol=TOL))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        traj = jax.block_until_ready(rb.simulate_batch(model, y0s, ts, rtol=TOL, atol=TOL))
        times.append(time.perf_counter() - t0)
    steps = np.asarray(traj.stats["num_steps"])
    return np.asarray(traj.ys.omega), float(np.median(times)), first, float(steps.mean())


def rhs(t, y):
    A, B, C = MOMENTS
    p, q, r = y
    return [(B - C) * q * r / A, (C - A) * r * p / B, (A - B) * p * q / C]


def run_scipy(w0, ts):
    t0 = time.perf_counter()
    out, steps = [], []
    for w in w0:
        sol = solve_ivp(rhs, (ts[0], ts[-1]), w, t_eval=ts, rtol=TOL, atol=TOL, method="RK45")
        out.append(sol.y.T)
        steps.append(sol.nfev / 6)
    return np.stack(out), time.perf_counter() - t0, float(np.mean(steps))


def main(sizes=(1, 10, 100, 1000), scipy_max=100, repeats=3, out="results/benchmarks"):
    ts = np.linspace(0.0, T_END, N_OUT)
    rows = []
    for n in sizes:
        w0 = initial_rates(n)
        ref = reference(w0, jnp.asarray(ts))
        w_rb, t_rb, first, steps_rb = run_rbdyn(w0, jnp.asarray(ts), repeats)
        row = {"batch": n, "rbdyn_s": t_rb, "rbdyn_first_call_s": first,
               "rbdyn_traj_per_s": n / t_rb, "rbdyn_mean_steps": steps_rb,
               "rbdyn_max_error": float(np.max(np.abs(w_rb - ref)))}
        m = min(n, scipy_max)  # the scipy loop is timed on at most `scipy_max` trajectories
        w_sp, t_sp, steps_sp = run_scipy(w0[:m], ts)
        row.update({"scipy_traj_per_s": m / t_sp, "scipy_mean_steps": steps_sp,
                    "scipy_max_error": float(np.max(np.abs(w_sp - ref[:m])))})
        row["speedup_vs_scipy"] = row["rbdyn_traj_per_s"] / row["scipy_traj_per_s"]
        rows.append(row)
    head = (f"{'batch':>6} {'rbdyn traj/s':>13} {'steps':>6} {'max err':>9} | "
            f"{'scipy traj/s':>12} {'steps':>6} {'max err':>9} | {'ratio':>7}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['batch']:>6} {r['rbdyn_traj_per_s']:>13.1f} {r['rbdyn_mean_steps']:>6.0f} "
              f"{r['rbdyn_max_error']:>9.1e} | {r['scipy_traj_per_s']:>12.1f} "
              f"{r['scipy_mean_steps']:>6.0f} {r['scipy_max_error']:>9.1e} | "
              f"{r['speedup_vs_scipy']:>6.1f}x")
    path = pathlib.Path(out)
    path.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.platform(), "cpus": jax.device_count(), "jax": jax.__version__,
            "rtol": TOL, "t_end": T_END, "n_out": N_OUT}
    (path / "throughput.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {path / 'throughput.json'}")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 100, 1000])
    p.add_argument("--scipy-max", type=int, default=100)
    p.add_argument("--out", default="results/benchmarks")
    args = p.parse_args()
    main(tuple(args.sizes), args.scipy_max, out=args.out)
