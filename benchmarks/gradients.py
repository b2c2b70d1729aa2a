"""Gradients of a batched trajectory loss with respect to the inertia: cost and accuracy of
reverse mode (three diffrax adjoints), forward mode (diffrax's `ForwardMode`), both modes
through the lane solver (its forward sensitivities) and central finite differences, each
beside the cost of one forward loss.

Setting: torque-free body with products of inertia,
J = [[2, 0.05, 0], [0.05, 3, 0.02], [0, 0.02, 4]], N trajectories (default 64) with
ω0 ~ N(0, 1) per axis (numpy `default_rng(0)`), identity initial attitude, t ∈ [0, 20] with 21
output times, Tsit5, rtol = atol = 1e-8, `max_steps` = 4096 for every solve, float64. Data:
the trajectories of J_data = J + diag(0.1, 0, 0) (the smallest moment 5 % larger) from the
same ω0, solved at rtol = atol = 1e-12. Not 1.05 J: the torque-free Euler equations
J ω' = J ω × ω are homogeneous in J, so 1.05 J has exactly the same ω(t) as J, and the loss
and its gradient would be zero (round-off) at θ0. Loss L(θ) = Σ |ω(t; θ) − ω_data|² over
trajectories and times, θ the 6 log-Cholesky parameters of J
(`rb.inertia.from_log_cholesky`), evaluated at θ0 = `to_log_cholesky(J)`.

Methods, each a `jax.jit`-ed function of θ (`compiler_options=rb.COMPILER_OPTIONS`, as
rbdyn_jax advises for a caller's jit): the forward loss through `simulate_batch`
(its default, `batching=rb.Vmap()` and the lane solver `rb.Lanes(16)`: fewer lanes than each
device's 32 trajectories, so that lanes refill longest-first and finish together; of 8, 16,
32 and 64 lanes, 16 gives the fastest `jax.jacfwd` here); `jax.grad` with
`RecursiveCheckpointAdjoint()` (diffrax's default), with `RecursiveCheckpointAdjoint(
checkpoints=4096)` (every step stored) and with `BacksolveAdjoint()`; `jax.jacfwd` with
`ForwardMode()`; `jax.jacfwd` and `jax.grad` through the lane solver; central
differences, h = 1e-6, 12 lane-solver losses (`lax.map` over the 12 perturbed θ).

The yardstick: central differences of the same loss with the numba-compiled Dormand–Prince
solver (`_baselines.numba_solve`, parallel over the trajectories), at equal accuracy: of the
tolerances 1e-8, 1e-10, 1e-12 and the steps h = 1e-3 … 1e-6, the cheapest pair (loosest
tolerance, then the fewest steps' error) whose gradient is as accurate as the lane solver's
`jax.grad`, or the most accurate pair if none is. Its time is one gradient (12 numba
solves of the batch) from NumPy θ, timed in the same rounds.
Timings: the first call (tracing + compilation + one run), then 7 rounds that call every
method once: the fastest call of each and its median; the ratios are to the default and
to the vmapped forward loss. Accuracy: the relative error max|g − g_ref| / max|g_ref|
against g_ref = `jax.grad` (`Vmap`, RecursiveCheckpointAdjoint) of the loss solved at
rtol = atol = 1e-12; for the forward rows, |L − L_ref| / |L_ref| of the loss value. A
method that fails has its error message in the table instead of numbers.

XLA: the script starts it with `rb.configure_xla(host_devices=2)`, as docs/performance.md advises:
its while loops compiled whole, and two host devices (unless XLA_FLAGS sets a count), so the
lane solver splits its batch over both cores; the vmapped `diffeqsolve` runs on one.

Run: `python benchmarks/gradients.py [--n 64] [--out DIR]` — prints a table and writes
DIR/gradients.json (DIR defaults to results/benchmarks).
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
import _baselines  # noqa: E402
import _report  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
J_DATA = J + np.diag([0.1, 0.0, 0.0])
T_END, N_OUT, TOL, REF_TOL = 20.0, 21, 1e-8, 1e-12
MAX_STEPS, LANES, H, REPEATS = 4096, 16, 1e-6, 7


def reference_rates(inertia, y0s, ts):
    """ω(t) (N, n, 3) of the body `inertia` at rtol = atol = REF_TOL."""
    traj = rb.simulate_batch(
        rb.RigidBody(jnp.asarray(inertia)),
        y0s,
        ts,
        rtol=REF_TOL,
        atol=REF_TOL,
        max_steps=MAX_STEPS,
        throw=True,
    )
    return traj.ys.omega


def problem(n, seed=0):
    """Initial states, output times, data (trajectories of J_DATA), θ0 and the loss at θ0
    solved at REF_TOL."""
    w0 = np.random.default_rng(seed).normal(size=(n, 3))
    y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1)))
    ts = jnp.linspace(0.0, T_END, N_OUT)
    data = reference_rates(J_DATA, y0s, ts)
    ref_loss = float(jnp.sum((reference_rates(J, y0s, ts) - data) ** 2))
    return y0s, ts, data, rb.inertia.to_log_cholesky(jnp.asarray(J)), ref_loss


def make_loss(y0s, ts, data, tol=TOL, **kw):
    """L(θ) through `simulate_batch(..., **kw)` (batching, adjoint)."""

    def loss(theta):
        model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
        traj = rb.simulate_batch(model, y0s, ts, rtol=tol, atol=tol, max_steps=MAX_STEPS, **kw)
        return jnp.sum((traj.ys.omega - data) ** 2)

    return loss


def central_differences(loss, h=H):
    """∇L by central differences: the 2 × 6 perturbed losses in one `lax.map`."""

    def grad(theta):
        e = h * jnp.eye(theta.shape[0], dtype=theta.dtype)
        f = jax.lax.map(loss, jnp.concatenate([theta + e, theta - e]))
        return (f[: theta.shape[0]] - f[theta.shape[0] :]) / (2 * h)

    return grad


def numba_loss(y0s, data, ts, tol):
    """L(θ) (NumPy θ) through the numba Dormand–Prince solver."""
    w0, q0 = np.asarray(y0s.omega), np.asarray(y0s.quat)
    data, ts = np.asarray(data), np.asarray(ts)

    def loss(theta):
        inertia = np.asarray(rb.inertia.from_log_cholesky(jnp.asarray(theta)))
        om = _baselines.numba_solve(
            "torque_free",
            {"inertia": inertia, "weight": 0.0, "com": np.zeros(3), "eps": 0.0},
            w0,
            q0,
            ts,
            tol,
            tol,
            MAX_STEPS,
        )["omega"]
        return float(np.sum((om - data) ** 2))

    return loss


def numba_central_differences(loss, h):
    def grad(theta):
        theta = np.asarray(theta)
        e = h * np.eye(theta.shape[0])
        return np.array([(loss(theta + d) - loss(theta - d)) / (2 * h) for d in e])

    return grad


def numba_equal_accuracy(y0s, ts, data, theta0, ref_grad, target):
    """(name, gradient function, its relative error) of the numba central differences at
    the cheapest tolerance and step as accurate as `target`, else the most accurate."""
    best = None
    for tol in (1e-8, 1e-10, 1e-12):
        for h in (1e-3, 1e-4, 1e-5, 1e-6):
            g = numba_central_differences(numba_loss(y0s, data, ts, tol), h)
            err = rel_error(g(theta0), ref_grad)
            if best is None or err < best[2]:
                best = (f"central differences, h={h:g}, numba rtol={tol:g}", g, err)
            if err <= target:
                return best[0], g, err
    return best


def methods(y0s, ts, data):
    """name -> (kind, function of θ): kind "loss" or "grad"."""
    default = make_loss(y0s, ts, data)  # `simulate_batch` chooses its batching
    plain = make_loss(y0s, ts, data, batching=rb.Vmap())
    lanes = make_loss(y0s, ts, data, batching=rb.Lanes(LANES))
    adj = diffrax.RecursiveCheckpointAdjoint
    return {
        "forward loss, default": ("loss", default),
        "forward loss, vmapped diffeqsolve": ("loss", plain),
        f"forward loss, lanes={LANES}": ("loss", lanes),
        "grad, default": ("grad", jax.grad(default)),
        "grad, RecursiveCheckpointAdjoint()": ("grad", jax.grad(plain)),
        f"grad, RecursiveCheckpointAdjoint(checkpoints={MAX_STEPS})": (
            "grad",
            jax.grad(make_loss(y0s, ts, data, adjoint=adj(checkpoints=MAX_STEPS))),
        ),
        "grad, BacksolveAdjoint()": (
            "grad",
            jax.grad(make_loss(y0s, ts, data, adjoint=diffrax.BacksolveAdjoint())),
        ),
        "jacfwd, ForwardMode()": (
            "grad",
            jax.jacfwd(make_loss(y0s, ts, data, adjoint=diffrax.ForwardMode())),
        ),
        f"jacfwd, lanes={LANES}": ("grad", jax.jacfwd(lanes)),
        f"grad, lanes={LANES}": ("grad", jax.grad(lanes)),
        f"central differences, h={H:g}, lanes": ("grad", central_differences(lanes)),
    }


def first_call(fn, theta):
    """The jitted `fn`, the wall time of its first call (tracing + compilation + one run)
    and its value, or the error message of a failure."""
    f = jax.jit(fn, compiler_options=rb.COMPILER_OPTIONS)
    try:
        t0 = time.perf_counter()
        out = jax.block_until_ready(f(theta))
        first = time.perf_counter() - t0
    except Exception as err:  # a method that does not work: report it, go on
        msg = str(err).strip().splitlines()
        return None, {"error": f"{type(err).__name__}: {msg[0] if msg else ''}"[:300]}
    return f, {"first_call_s": first, "value": np.asarray(out)}


def timings(fns, theta, repeats):
    """Per method, the fastest and the median of `repeats` calls, taken in rounds that call
    every method once: a machine's speed can drift within minutes (a shared or virtual
    machine's most of all), and a drift then slows every method of a round alike instead
    of one method's calls."""
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(theta))
            times[name].append(time.perf_counter() - t0)
    return {
        name: {"time_s": float(np.min(t)), "median_s": float(np.median(t))}
        for name, t in times.items()
    }


def rel_error(value, ref):
    return float(np.max(np.abs(value - ref)) / np.max(np.abs(ref)))


def print_table(rows):
    w = max(len(r["method"]) for r in rows)
    head = (
        f"{'method':<{w}} | {'first call s':>12} | {'time ms':>9} | {'× default fwd':>13} | "
        f"{'× vmap fwd':>10} | {'median ms':>9} | {'rel. error':>10}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        if "error" in r:
            print(f"{r['method']:<{w}} | failed: {r['error']}")
            continue
        print(
            f"{r['method']:<{w}} | {r['first_call_s']:>12.2f} | {1e3 * r['time_s']:>9.2f} | "
            f"{r['x_default_forward']:>13.2f} | {r['x_vmap_forward']:>10.2f} | "
            f"{1e3 * r['median_s']:>9.2f} | "
            f"{r['rel_error']:>10.1e}"
        )


def main(n=64, out="results/benchmarks", repeats=REPEATS, only=None):
    """`only`: run just the methods whose name starts with one of these strings (the two
    forward rows, the baselines of the ratios, always run)."""
    y0s, ts, data, theta0, ref_loss = problem(n)
    ref_grad = jax.jit(
        jax.grad(make_loss(y0s, ts, data, tol=REF_TOL, batching=rb.Vmap())),
        compiler_options=rb.COMPILER_OPTIONS,
    )(theta0)
    ref = {"loss": np.asarray(ref_loss), "grad": np.asarray(ref_grad)}
    rows, jitted = [], {}
    for name, (kind, fn) in methods(y0s, ts, data).items():
        if only is not None and kind != "loss" and not name.startswith(tuple(only)):
            continue
        f, r = first_call(fn, theta0)
        r = {"method": name, "kind": kind, **r}
        if f is not None:
            jitted[name] = f
            r["rel_error"] = rel_error(r["value"], ref[kind])
            r["value"] = r["value"].tolist()
        rows.append(r)
    lane_grad = next((r for r in rows if r["method"] == "grad, default"), None)
    if lane_grad is not None and "rel_error" in lane_grad:
        _baselines.warmup()
        name, g, err = numba_equal_accuracy(
            y0s, ts, data, np.asarray(theta0), ref["grad"], lane_grad["rel_error"]
        )
        t0 = time.perf_counter()
        value = g(np.asarray(theta0))
        rows.append(
            {
                "method": name,
                "kind": "grad",
                "first_call_s": time.perf_counter() - t0,
                "value": value.tolist(),
                "rel_error": err,
            }
        )
        jitted[name] = g
    measured = timings(jitted, theta0, repeats)
    for r in rows:
        r.update(measured.get(r["method"], {}))
    base = {r["method"]: r.get("time_s") for r in rows}
    default, plain = base["forward loss, default"], base["forward loss, vmapped diffeqsolve"]
    for r in rows:
        if "time_s" in r:
            r["x_default_forward"] = r["time_s"] / default if default else float("nan")
            r["x_vmap_forward"] = r["time_s"] / plain if plain else float("nan")
    print(
        f"reference (rtol = atol = {REF_TOL:g}): L = {float(ref['loss']):.6e}, "
        f"max |∇L| = {np.max(np.abs(ref['grad'])):.6e}"
    )
    print_table(rows)
    meta = {
        "n": n,
        "t_end": T_END,
        "n_out": N_OUT,
        "rtol": TOL,
        "ref_rtol": REF_TOL,
        "max_steps": MAX_STEPS,
        "lanes": LANES,
        "fd_step": H,
        "repeats": repeats,
        "inertia": J.tolist(),
        "inertia_data": J_DATA.tolist(),
        "theta0": np.asarray(theta0).tolist(),
        "ref_loss": float(ref["loss"]),
        "ref_grad": ref["grad"].tolist(),
    }
    print(f"wrote {_report.write_json(out, 'gradients', meta, rows)}")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=64, help="trajectories (default 64)")
    p.add_argument("--out", default="results/benchmarks", help="output folder")
    args = p.parse_args()
    main(args.n, args.out)
