"""Throughput of batched forward solves, side by side in one run: rbdyn_jax's default call
(`simulate_batch(model, y0s, ts)`, which picks its batching), the lane solver with a given
lane count (`batching=rb.Lanes(L)`), the vmapped `diffeqsolve` (`batching=rb.Vmap()`), a
numba-compiled per-trajectory Dormand–Prince 5(4) (the near-limit yardstick) and a scipy
`solve_ivp` loop, with the accuracy of each printed beside its speed.

Setting: J = [[2, 0.05, 0], [0.05, 3, 0.02], [0, 0.02, 4]],
ω0 ~ N(0, 1) per axis (seed 0), identity initial attitude, t ∈ [0, 100], 101 outputs,
rtol = atol = 1e-8, float64, three models (`benchmarks/_baselines.py` writes the same
equations independently):

- `torque_free`: accuracy against the Jacobi elliptic solution (docs/physics.md#torque-free-motion,
  in principal axes);
- `heavy_top`: uniform gravity, weight 1 at r_c = (0, 0, 0.5);
- `gravity_gradient`: M = ε γ × Jγ with ε = 3 (orbit rate 1);
  for these two the reference is the numba solver at rtol = atol = 1e-12 on the first
  `--ref-max` trajectories (errors are measured on those).

rbdyn_jax uses Tsit5 (its default), numba and scipy RK45 use Dormand–Prince 5(4) with the
same tolerances; the error columns show what each delivers. XLA runs a while loop on one
core, so the script starts XLA with one host device per core and its while loops compiled
whole (`rb.configure_xla(host_devices=<cores>)`, as docs/performance.md advises; a count already in
XLA_FLAGS is kept) and the lane solver splits the batch over them; numba uses its default
thread count (the cores). The scipy loop is timed on at most `--scipy-max` trajectories (0:
not run) and the plain vmapped solve on batches up to `--plain-max` (its lockstep cost grows
with the batch). Compilation is excluded from the rates (a first call is made per shape and
reported). The `lanes` column runs `--lanes` lanes per device (64 by default, as
`rbdyn sweep` does); the `default` column lets `simulate_batch` choose.

Run: `python benchmarks/throughput.py [--sizes 1 10 100 1000 10000] [--models …]
[--lanes 64]` — prints a table per model and writes results/benchmarks/throughput.json.
"""

import os

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla(host_devices=os.cpu_count() or 1)

import argparse  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import _baselines  # noqa: E402
import _report  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
T_END, N_OUT, TOL = 100.0, 101, 1e-8
WEIGHT, COM, EPS = 1.0, np.array([0.0, 0.0, 0.5]), 3.0
MODELS = ("torque_free", "heavy_top", "gravity_gradient")


def rbdyn_model(name):
    torque = {
        "torque_free": None,
        "heavy_top": rb.UniformGravity(WEIGHT, jnp.asarray(COM)),
        "gravity_gradient": rb.GravityGradient(EPS),
    }[name]
    return rb.RigidBody(jnp.asarray(J), torque)


def baseline_params(name):
    return {"inertia": J, "weight": WEIGHT, "com": COM, "eps": EPS}


def initial_rates(n, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3))


def elliptic(w0, ts):
    moments, axes = rb.inertia.principal_axes(jnp.asarray(J))
    wp = jnp.asarray(w0) @ axes  # ω in principal axes: axesᵀ ω for each row

    def one(w):
        return rb.analytic.torque_free_elliptic(moments, w, jnp.asarray(ts))

    return np.asarray(jax.vmap(one)(wp) @ axes.T)


def timed(fn, repeats):
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, first, float(np.median(times))


def run_rbdyn(name, w0, ts, batching, repeats):
    model = rbdyn_model(name)
    y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (len(w0), 1)))

    def call():
        tr = rb.simulate_batch(model, y0s, jnp.asarray(ts), rtol=TOL, atol=TOL, batching=batching)
        return jax.block_until_ready(tr)

    tr, first, t = timed(call, repeats)
    return np.asarray(tr.ys.omega), first, t, float(np.mean(tr.stats["num_steps"]))


def run_baseline(solve, name, w0, ts, repeats, tol=TOL, **kw):
    q0 = np.tile([1.0, 0.0, 0.0, 0.0], (len(w0), 1))
    out, first, t = timed(
        lambda: solve(name, baseline_params(name), w0, q0, ts, tol, tol, **kw), repeats
    )
    return out["omega"], first, t, float(np.mean(out["steps"]))


def numba_equal_accuracy(name, w0, ts, repeats, ref, target):
    """numba at the loosest tolerance TOL/2ᵏ (k = 0 … 5) whose median error is at most
    `target` (the lane solver's median error): the yardstick at equal accuracy, the fair
    comparison of speeds. The error is tried on the trajectories with a reference, then the
    whole batch is timed at that tolerance."""
    q0 = np.tile([1.0, 0.0, 0.0, 0.0], (len(ref), 1))
    for k in range(6):
        tol = TOL / 2**k
        om = _baselines.numba_solve(name, baseline_params(name), w0[: len(ref)], q0, ts, tol, tol)[
            "omega"
        ]
        if median_error(om, ref) <= target:
            break
    return dict(
        record(run_baseline(_baselines.numba_solve, name, w0, ts, repeats, tol=tol), len(w0), ref),
        tol=tol,
    )


def median_error(omega, ref):
    """The median over trajectories of max_t |ω − ω_ref| (robust to the few chaotic heavy
    tops whose error at t = 100 is O(1) for every method)."""
    m = min(len(omega), len(ref))
    return float(np.median(np.max(np.abs(omega[:m] - ref[:m]), axis=(1, 2))))


def reference(name, w0, ts):
    if name == "torque_free":
        return elliptic(w0, ts)
    q0 = np.tile([1.0, 0.0, 0.0, 0.0], (len(w0), 1))
    return _baselines.numba_solve(name, baseline_params(name), w0, q0, ts, 1e-12, 1e-12)["omega"]


def record(result, count, ref):
    """Rate, first call, mean steps and the worst |ω − ω_ref| over the trajectories that
    have a reference."""
    omega, first, t, steps = result
    m = min(len(omega), len(ref))
    return {
        "traj_per_s": count / t,
        "first_call_s": first,
        "mean_steps": steps,
        "max_error": float(np.max(np.abs(omega[:m] - ref[:m]))),
        "median_error": median_error(omega, ref),
    }


def main(sizes, models, lanes, scipy_max, plain_max, ref_max, out):
    ts = np.linspace(0.0, T_END, N_OUT)
    _baselines.warmup()
    rows = []
    for name in models:
        for n in sizes:
            w0 = initial_rates(n)
            ref = reference(name, w0[: min(n, ref_max)], ts)
            repeats = 3 if n <= 1000 else 1
            row = {
                "model": name,
                "batch": n,
                "default": record(run_rbdyn(name, w0, ts, None, repeats), n, ref),
                "lanes": record(run_rbdyn(name, w0, ts, rb.Lanes(lanes), repeats), n, ref),
                "numba": record(
                    run_baseline(_baselines.numba_solve, name, w0, ts, repeats), n, ref
                ),
            }
            row["numba_equal"] = numba_equal_accuracy(
                name, w0, ts, repeats, ref, row["lanes"]["median_error"]
            )
            if n <= plain_max:
                row["plain"] = record(run_rbdyn(name, w0, ts, rb.Vmap(), repeats), n, ref)
            k = min(n, scipy_max)
            if k > 0:
                row["scipy"] = record(
                    run_baseline(_baselines.scipy_solve, name, w0[:k], ts, 1, method="RK45"),
                    k,
                    ref,
                )
            rows.append(row)
            print_row(row)
    meta = {"rtol": TOL, "t_end": T_END, "n_out": N_OUT, "lanes": lanes, "scipy_max": scipy_max}
    print(f"wrote {_report.write_json(out, 'throughput', meta, rows)}")
    return rows


HEAD = (
    f"{'model':>16} {'batch':>6} | {'default':>8} {'err':>7} | "
    f"{'lanes traj/s':>12} {'steps':>5} {'err':>7} "
    f"{'med':>7} | {'plain':>7} {'err':>7} | {'numba':>7} {'steps':>5} {'err':>7} "
    f"{'med':>7} | {'numba=':>7} {'tol':>7} {'med':>7} | {'scipy':>6} {'err':>7} | "
    f"{'default/numba':>13} {'lanes/numba':>11} {'lanes/numba=':>12} {'lanes/scipy':>11} "
    f"{'lanes/plain':>11}"
)


def print_row(r, _printed=[]):  # noqa: B006 (print the header once)
    if not _printed:
        print(HEAD)
        print("-" * len(HEAD))
        _printed.append(True)
    de, la, nu, eq = r["default"], r["lanes"], r["numba"], r["numba_equal"]
    pl, sp = r.get("plain"), r.get("scipy")
    scipy = f"{sp['traj_per_s']:>6.1f} {sp['max_error']:>7.1e}" if sp else f"{'—':>6} {'':>7}"
    ratio_scipy = f"{la['traj_per_s'] / sp['traj_per_s']:>10.0f}x" if sp else f"{'—':>11}"
    plain = f"{pl['traj_per_s']:>7.0f} {pl['max_error']:>7.1e}" if pl else f"{'—':>7} {'':>7}"
    ratio_plain = f"{la['traj_per_s'] / pl['traj_per_s']:>10.1f}x" if pl else f"{'—':>11}"
    print(
        f"{r['model']:>16} {r['batch']:>6} | {de['traj_per_s']:>8.0f} "
        f"{de['max_error']:>7.1e} | {la['traj_per_s']:>12.0f} "
        f"{la['mean_steps']:>5.0f} {la['max_error']:>7.1e} {la['median_error']:>7.1e} | "
        f"{plain} | {nu['traj_per_s']:>7.0f} {nu['mean_steps']:>5.0f} "
        f"{nu['max_error']:>7.1e} {nu['median_error']:>7.1e} | {eq['traj_per_s']:>7.0f} "
        f"{eq['tol']:>7.1e} {eq['median_error']:>7.1e} | "
        f"{scipy} | "
        f"{de['traj_per_s'] / nu['traj_per_s']:>12.2f}x "
        f"{la['traj_per_s'] / nu['traj_per_s']:>10.2f}x "
        f"{la['traj_per_s'] / eq['traj_per_s']:>11.2f}x "
        f"{ratio_scipy} {ratio_plain}",
        flush=True,
    )


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 100, 1000, 10000])
    p.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    p.add_argument("--lanes", type=int, default=64)
    p.add_argument("--scipy-max", type=int, default=20)
    p.add_argument("--plain-max", type=int, default=1000)
    p.add_argument("--ref-max", type=int, default=1000)
    p.add_argument("--out", default="results/benchmarks")
    a = p.parse_args()
    main(a.sizes, a.models, a.lanes, a.scipy_max, a.plain_max, a.ref_max, a.out)
