"""Work–precision of batched forward solves: the largest error against the Jacobi elliptic
solution vs the wall time per trajectory, over a range of tolerances, for diffrax's Tsit5,
Dopri5 and Dopri8 through `simulate_batch(..., batching=rb.Vmap())` (vmapped `diffeqsolve`),
the lane solver (`batching=rb.Lanes(64)`: 4 trajectories per lane at the default N = 512 on two
devices, so lanes refill) with Tsit5 and Dopri5, and the numba Dormand–Prince 5(4)
yardstick of `benchmarks/_baselines.py`.

Setting: torque-free body with products of inertia,
J = [[2, 0.05, 0], [0.05, 3, 0.02], [0, 0.02, 4]], ω0 ~ N(0, 1) per axis (numpy
`default_rng(0)`), identity initial attitude, t ∈ [0, 100] with 101 output times,
rtol = atol = tol for tol in 1e-5 … 1e-11, float64. The exact ω(t) is the elliptic solution in
the principal axes (`rb.inertia.principal_axes`, J = C diag(I) Cᵀ, ω_principal = Cᵀ ω),
rotated back to the body axes. Error: max over trajectories and output times of |ω − ω_exact|
(absolute; |ω| is O(1)). Time: median of 3 calls per (method, tol) after one compiling call per
method (tolerances are runtime arrays: changing them does not recompile). Steps: mean
accepted + rejected steps per trajectory.

XLA: the script starts it with `rb.configure_xla(host_devices=2)`, as docs/performance.md advises:
its while loops compiled whole, and two host devices (unless XLA_FLAGS sets a count), so the
lane solver splits its batch over both cores (`devices` default: all). The vmapped
`diffeqsolve` runs on one device; numba runs `prange` over its default thread count (the
cores).

Run: `python benchmarks/work_precision.py [--n 512] [--tols 1e-5 1e-6 ...] [--out DIR]` —
prints a table, writes DIR/work_precision.json and DIR/work_precision.png (log-log error
vs µs per trajectory, one line per method); DIR defaults to results/benchmarks.
"""

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla(host_devices=2)

import argparse  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _report  # noqa: E402
from _baselines import numba_solve  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
T_END, N_OUT, LANES, REPEATS = 100.0, 101, 64, 3
TOLS = (1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11)
# name -> (diffrax solver, lanes); None as the solver marks the numba yardstick.
METHODS = {
    "Tsit5": (diffrax.Tsit5(), None),
    "Dopri5": (diffrax.Dopri5(), None),
    "Dopri8": (diffrax.Dopri8(), None),
    "Tsit5 lanes": (diffrax.Tsit5(), LANES),
    "Dopri5 lanes": (diffrax.Dopri5(), LANES),
    "numba DP5": (None, None),
}


def initial_rates(n, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3))


def exact_rates(w0, ts):
    """ω(t) from the elliptic solution in the principal axes, in body axes, (N, n, 3)."""
    moments, axes = rb.inertia.principal_axes(jnp.asarray(J))
    wp0 = jnp.asarray(w0) @ axes  # rows: Cᵀ ω0
    wp = jax.vmap(lambda w: rb.analytic.torque_free_elliptic(moments, w, ts))(wp0)
    return np.asarray(wp @ axes.T)  # rows: C ω_principal


def timed(fn, repeats):
    """Median wall time of `repeats` calls of `fn` (each waited for with
    `block_until_ready`) and the last result."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def rbdyn_runner(solver, lanes, w0, ts):
    """`tol -> (omega (N, n, 3), steps (N,), all successful)` through `simulate_batch`."""
    model = rb.RigidBody(jnp.asarray(J))
    y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (len(w0), 1)))
    ts = jnp.asarray(ts)

    def run(tol):
        traj = rb.simulate_batch(
            model,
            y0s,
            ts,
            solver=solver,
            rtol=tol,
            atol=tol,
            batching=rb.Vmap() if lanes is None else rb.Lanes(lanes),
        )
        ok = jnp.all(traj.result == rb.RESULTS.successful)
        return traj.ys.omega, traj.stats["num_steps"], ok

    return run


def numba_runner(w0, ts):
    quat0 = np.tile([1.0, 0.0, 0.0, 0.0], (len(w0), 1))

    def run(tol):
        out = numba_solve("torque_free", {"inertia": J}, w0, quat0, ts, tol, tol)
        return out["omega"], out["steps"], bool(np.all(out["status"] == 0))

    return run


def measure(name, run, tols, ref, repeats):
    """One row per tol for one method; the first call (compiling) is timed separately."""
    t0 = time.perf_counter()
    jax.block_until_ready(run(tols[0]))
    first = time.perf_counter() - t0
    rows = []
    for tol in tols:
        wall, (omega, steps, ok) = timed(lambda tol=tol: run(tol), repeats)
        n = ref.shape[0]
        rows.append(
            {
                "method": name,
                "tol": tol,
                "us_per_traj": 1e6 * wall / n,
                "wall_s": wall,
                "first_call_s": first,
                "mean_steps": float(np.mean(np.asarray(steps))),
                "max_error": float(np.max(np.abs(np.asarray(omega) - ref))),
                "all_successful": bool(ok),
            }
        )
    return rows


def print_table(rows):
    head = (
        f"{'method':<13} {'tol':>7} {'µs/traj':>9} {'steps':>7} {'max |Δω|':>9} "
        f"{'first call s':>12}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        flag = "" if r["all_successful"] else "  (some solves failed)"
        print(
            f"{r['method']:<13} {r['tol']:>7.0e} {r['us_per_traj']:>9.1f} "
            f"{r['mean_steps']:>7.0f} {r['max_error']:>9.1e} {r['first_call_s']:>12.2f}{flag}"
        )


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    for name in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == name]
        ax.loglog(
            [r["us_per_traj"] for r in sel],
            [r["max_error"] for r in sel],
            marker="o",
            label=name,
            linestyle="--" if name.startswith("numba") else "-",
        )
    ax.set_xlabel("wall time per trajectory (µs)")
    ax.set_ylabel("max |ω − ω_exact|")
    ax.set_title(f"Work–precision, torque-free body, t ∈ [0, {T_END:g}], N = {rows[0]['n']}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(n=512, tols=TOLS, out="results/benchmarks", repeats=REPEATS, methods=tuple(METHODS)):
    """`methods`: the names of METHODS to run (default all)."""
    tols = tuple(float(t) for t in tols)
    w0 = initial_rates(n)
    ts = np.linspace(0.0, T_END, N_OUT)
    ref = exact_rates(w0, jnp.asarray(ts))
    rows = []
    for name in methods:
        solver, lanes = METHODS[name]
        run = numba_runner(w0, ts) if solver is None else rbdyn_runner(solver, lanes, w0, ts)
        rows += measure(name, run, tols, ref, repeats)
    for r in rows:
        r["n"] = n
    print_table(rows)
    meta = {
        "n": n,
        "t_end": T_END,
        "n_out": N_OUT,
        "lanes": LANES,
        "repeats": repeats,
        "inertia": J.tolist(),
    }
    file = _report.write_json(out, "work_precision", meta, rows)
    plot(rows, file.with_suffix(".png"))
    print(f"wrote {file} and {file.with_suffix('.png')}")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=512, help="trajectories (default 512)")
    p.add_argument(
        "--tols",
        type=float,
        nargs="+",
        default=list(TOLS),
        help="rtol = atol values (default 1e-5 … 1e-11)",
    )
    p.add_argument("--out", default="results/benchmarks", help="output folder")
    args = p.parse_args()
    main(args.n, tuple(args.tols), args.out)
