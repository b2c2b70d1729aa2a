"""Long horizons: the energy and |L| errors of the torque-free body against time, to 10⁶
periods, for diffrax's Tsit5 at rtol = atol = 1e-8, 1e-10 and 1e-12 and for
`rb.LiePoissonSplitting` of orders 2, 4 and 6, side by side in one run, with the cost per
period and the global error at 10⁴ periods.

Setting: J = [[2, 0.05, 0], [0.05, 3, 0.02], [0, 0.02, 4]] (the throughput benchmark's), ω0 =
(0.8, 0, 0.6) in its principal axes (elliptic modulus k² = 0.89, period T = 29.41), identity
attitude, float64, one trajectory per method through `rb.simulate`. The outputs are
`--per-decade` times drawn log-uniformly in each decade from T/10 to the horizon (times
commensurate with T would sample the energy error at one phase of its oscillation), plus
10⁴ T exactly. Errors: relative energy error |E/E0 − 1|, relative error of the inertial
|L| = |R(q) J ω|, the quaternion's norm before the output's renormalisation
(`stats["norm_drift"]`), and the global error |ω − ω_exact| / |ω0| at 10⁴ T against the
Jacobi elliptic solution (`rb.analytic.torque_free_elliptic`). The curves keep the largest
error in each of 10 log-spaced bins per decade. Time: after every method's long solve (each
compiled first by a solve of 10 periods with the same outputs' shape; the steps and
tolerances are runtime arrays), `--repeats` rounds of solves over 10⁴ periods (the horizon
if shorter), the methods in turn within each round; cost per period = the fastest round's
wall time / periods (the long solve's wall time is kept as `wall_s`).

The splitting methods run at steps chosen for comparable cost (order 2 at T/300, order 4 at
T/100) and, for order 6, at T/50, T/100 and T/300. The targets (`targets`) are checked on
order 6 at T/50: |L| ≤ 1e-12, energy ≤ 1e-8 with no trend (largest error over the last
decade within 2× of that over periods 10–10²), cost per period ≤ 3× Tsit5's at 1e-10,
global error at 10⁴ periods below Tsit5's at 1e-10; and on order 6 at T/300 an energy
error ≤ 1e-13 at a cost per period ≤ 3× Tsit5's at 1e-10.

XLA: one device (`rb.configure_xla(host_devices=1)`), while loops compiled whole.

Potential torques: the same body as a heavy top (`UniformGravity`, weight 1 at r_c = (0, 0,
0.5)) and as a gravity-gradient satellite (`GravityGradient(3)`), from the attitude of ZXZ
Euler angles (0.3, 0.7, 0.2), over `--potential-periods` (10⁵) periods T of the torque-free
body (their fastest oscillations are shorter than T: the horizon spans more of them), Tsit5
at 1e-10 against order 6 at T/200: the energy error against time and its largest values
over periods 10–10² and over the last decade (the energy is bounded where the second is
within 2× of the first).

Run: `python benchmarks/long_horizon.py [--periods 1e6] [--potential-periods 1e5]
[--per-decade 300] [--repeats 3] [--methods …] [--out DIR]` — prints the tables, writes
DIR/long_horizon.json and DIR/long_horizon.png (log–log energy and |L| errors against
periods); DIR defaults to results/benchmarks. The full run takes about 25 minutes on one
core, most of it Tsit5 at 1e-12.
"""

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla(host_devices=1)

import argparse  # noqa: E402
import math  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _report  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
W0_PRINCIPAL = np.array([0.8, 0.0, 0.6])
GLOBAL_AT = 1e4  # periods: where the global error is measured
COST_PERIODS = 1e4  # periods of the timed rounds
BINS_PER_DECADE = 10
# Tsit5's step budget per period (`max_steps`): 731 measured at 1e-12 on the torque-free
# body, 778 at 1e-10 on the gravity-gradient body.
TSIT5_STEPS = 1600
# name -> ("tsit5", rtol) or ("splitting", order, steps per period)
METHODS = {
    "Tsit5 1e-8": ("tsit5", 1e-8),
    "Tsit5 1e-10": ("tsit5", 1e-10),
    "Tsit5 1e-12": ("tsit5", 1e-12),
    "Splitting 2, T/300": ("splitting", 2, 300),
    "Splitting 4, T/100": ("splitting", 4, 100),
    "Splitting 6, T/50": ("splitting", 6, 50),
    "Splitting 6, T/100": ("splitting", 6, 100),
    "Splitting 6, T/300": ("splitting", 6, 300),
}
TARGET_METHOD, BASELINE = "Splitting 6, T/50", "Tsit5 1e-10"
FINE_METHOD = "Splitting 6, T/300"  # energy ≤ 1e-13 at ≤ 3× the baseline's cost
# The bodies under a potential torque: name -> torque; their methods, from the same
# initial attitude (ZXZ Euler angles).
POTENTIALS = {
    "heavy top": lambda: rb.UniformGravity(1.0, jnp.array([0.0, 0.0, 0.5])),
    "gravity gradient": lambda: rb.GravityGradient(3.0),
}
POTENTIAL_METHODS = {"Tsit5 1e-10": ("tsit5", 1e-10), "Splitting 6, T/200": ("splitting", 6, 200)}
POTENTIAL_ATTITUDE = (0.3, 0.7, 0.2)


def problem():
    """The model, the initial state, the principal moments and axes and the period."""
    moments, axes = rb.inertia.principal_axes(jnp.asarray(J))
    w0p = jnp.asarray(W0_PRINCIPAL)
    period = float(rb.analytic.torque_free_elliptic_period(moments, w0p))
    y0 = rb.State(axes @ w0p, jnp.array([1.0, 0.0, 0.0, 0.0]))
    return rb.RigidBody(jnp.asarray(J)), y0, moments, axes, period


def output_periods(periods: float, per_decade: int, seed: int = 0):
    """0, `per_decade` log-uniform times in each decade from 0.1 to `periods`, 10⁴ (where
    within the horizon) and `periods` itself, sorted, in periods; and which of them are
    the random ones (the others, whole numbers of periods, see the energy error at one
    phase of its oscillation and are left out of the curves and windows)."""
    rng = np.random.default_rng(seed)
    top = math.log10(periods)
    decades = np.arange(-1, math.ceil(top))
    t = 10.0 ** (decades[:, None] + rng.uniform(0, 1, (len(decades), per_decade)))
    t = t[t < periods]
    extra = np.array([0.0, periods] + ([GLOBAL_AT] if GLOBAL_AT < periods else []))
    p = np.unique(np.concatenate([t.ravel(), extra]))
    return p, ~np.isin(p, extra)


def solve(spec, model, y0, ts, period, max_steps):
    if spec[0] == "tsit5":
        return rb.simulate(model, y0, ts, rtol=spec[1], atol=spec[1], max_steps=max_steps)
    return rb.simulate(
        model,
        y0,
        ts,
        solver=rb.LiePoissonSplitting(spec[1]),
        dt0=jnp.asarray(period / spec[2]),
        max_steps=max_steps,
    )


def envelope(p, err):
    """The largest error in each of `BINS_PER_DECADE` log-spaced bins per decade of the
    output times `p` (periods > 0): [bin centres, maxima], empty bins left out."""
    bins = np.floor(np.log10(p) * BINS_PER_DECADE)
    centres, maxima = [], []
    for b in np.unique(bins):
        centres.append(float(10.0 ** ((b + 0.5) / BINS_PER_DECADE)))
        maxima.append(float(err[bins == b].max()))
    return [centres, maxima]


def measure(name, spec, model, y0, moments, axes, period, periods, per_decade, body="torque-free"):
    """A method's long solve of `body` (its `model` from `y0`): the row of its errors,
    steps and wall time. For a body under a torque only the energy is conserved: its row
    has no |L| and no global error."""
    free = body == "torque-free"
    p, random = output_periods(periods, per_decade)
    ts = jnp.asarray(p * period)
    steps_per_period = TSIT5_STEPS if spec[0] == "tsit5" else spec[2]
    max_steps = int(periods * steps_per_period * 1.1) + 1000
    warm = jnp.asarray(p / p[-1] * 10.0 * period)  # 10 periods, the same shapes
    jax.block_until_ready(solve(spec, model, y0, warm, period, max_steps))
    t0 = time.perf_counter()
    traj = solve(spec, model, y0, ts, period, max_steps)
    jax.block_until_ready(traj)
    wall = time.perf_counter() - t0
    assert int(rb.integrate.result_code(traj.result)) == 0, (name, traj.result)
    energy = np.asarray(rb.invariants.energy(model, traj))
    energy = np.abs(energy / energy[0] - 1.0)
    row = {
        "method": name,
        "body": body,
        "kind": spec[0],
        "horizon_periods": periods,
        "period": period,
        "outputs": len(p),
        "steps": int(traj.stats["num_steps"]),
        "steps_per_period": int(traj.stats["num_steps"]) / periods,
        "wall_s": wall,
        "energy_max": float(energy.max()),
        "quat_norm_drift": float(traj.stats["norm_drift"]),
    }
    if free:  # |L| is conserved by the torque-free body only
        L = np.linalg.norm(
            np.asarray(rb.invariants.angular_momentum_inertial(model, traj)), axis=-1
        )
        L = np.abs(L / L[0] - 1.0)
        row["L_max"] = float(L.max())
    row.update(
        {"rtol": spec[1]} if spec[0] == "tsit5" else {"order": spec[1], "dt_periods": 1.0 / spec[2]}
    )
    early = random & (p >= 10) & (p <= 100)
    late = random & (p >= periods / 10)
    row["energy_10_100"] = float(energy[early].max()) if early.any() else None
    row["energy_last_decade"] = float(energy[late].max())
    curve = {"energy": envelope(p[random], energy[random])}
    if not free:
        row["curve"] = curve
        return row
    row["L_last_decade"] = float(L[late].max())
    if GLOBAL_AT <= periods:
        i = int(np.searchsorted(p, GLOBAL_AT))
        exact = (
            np.asarray(axes)
            @ np.asarray(
                rb.analytic.torque_free_elliptic(
                    moments, jnp.asarray(W0_PRINCIPAL), jnp.asarray([0.0, GLOBAL_AT * period])
                )
            )[-1]
        )
        row["global_error_1e4"] = float(
            np.linalg.norm(np.asarray(traj.ys.omega[i]) - exact) / np.linalg.norm(W0_PRINCIPAL)
        )
    row["curve"] = {**curve, "L": envelope(p[random], L[random])}
    return row


def cost(rows, model, y0, period, periods, per_decade, repeats):
    """µs per period of each method (in `rows`): the fastest of `repeats` rounds, each
    solving every method in turn over `COST_PERIODS` periods (the horizon if shorter)."""
    span = min(COST_PERIODS, periods)
    p, _ = output_periods(periods, per_decade)
    ts = jnp.asarray(p / p[-1] * span * period)  # the long solve's shapes: compiled
    best = {r["method"]: math.inf for r in rows}
    for _ in range(repeats):
        for r in rows:
            spec = METHODS[r["method"]]
            max_steps = int(periods * (TSIT5_STEPS if spec[0] == "tsit5" else spec[2]) * 1.1) + 1000
            t0 = time.perf_counter()
            jax.block_until_ready(solve(spec, model, y0, ts, period, max_steps))
            best[r["method"]] = min(best[r["method"]], time.perf_counter() - t0)
    for r in rows:
        r["cost_periods"] = span
        r["us_per_period"] = 1e6 * best[r["method"]] / span


def targets(rows, potentials=()) -> dict:
    """The targets, checked on `TARGET_METHOD` and `FINE_METHOD` against `BASELINE`, and
    the splitting's energy bounded on each body of `potentials` (rows)."""
    by = {r["method"]: r for r in rows}
    if TARGET_METHOD not in by or BASELINE not in by:
        return {}
    t, b = by[TARGET_METHOD], by[BASELINE]
    out = {
        "method": TARGET_METHOD,
        "baseline": BASELINE,
        "L_le_1e-12": t["L_max"] <= 1e-12,
        "energy_le_1e-8": t["energy_max"] <= 1e-8,
        "cost_ratio": t["us_per_period"] / b["us_per_period"],
    }
    out["cost_le_3x"] = out["cost_ratio"] <= 3.0
    if t["energy_10_100"] is not None:
        out["energy_bounded"] = t["energy_last_decade"] <= 2.0 * t["energy_10_100"]
    if "global_error_1e4" in t:
        out["global_below_baseline"] = t["global_error_1e4"] < b["global_error_1e4"]
    if FINE_METHOD in by:
        f = by[FINE_METHOD]
        out["fine_method"] = FINE_METHOD
        out["fine_energy_le_1e-13"] = f["energy_max"] <= 1e-13
        out["fine_cost_ratio"] = f["us_per_period"] / b["us_per_period"]
    kicked = [r for r in potentials if r["kind"] == "splitting" and r["energy_10_100"]]
    if kicked:
        out["potentials_bounded"] = all(
            r["energy_last_decade"] <= 2.0 * r["energy_10_100"] for r in kicked
        )
    return out


def print_table(rows, checks, potentials=()):
    head = (
        f"{'method':<20} {'steps/T':>8} {'µs/T':>8} {'× Tsit5 1e-10':>13} {'max |ΔE/E|':>10} "
        f"{'E 10–10²':>9} {'E last dec.':>11} {'max |Δ|L||':>10} {'|q| − 1':>8} "
        f"{'global 1e4':>10}"
    )
    print(head)
    print("-" * len(head))
    base = {r["method"]: r for r in rows}.get(BASELINE)
    for r in rows:
        ratio = r["us_per_period"] / base["us_per_period"] if base else float("nan")
        g = r.get("global_error_1e4", float("nan"))
        e1 = r["energy_10_100"] if r["energy_10_100"] is not None else float("nan")
        print(
            f"{r['method']:<20} {r['steps_per_period']:>8.0f} {r['us_per_period']:>8.1f} "
            f"{ratio:>13.2f} {r['energy_max']:>10.1e} {e1:>9.1e} "
            f"{r['energy_last_decade']:>11.1e} {r['L_max']:>10.1e} "
            f"{r['quat_norm_drift']:>8.0e} {g:>10.1e}"
        )
    if potentials:
        print()
        head = (
            f"{'body':<17} {'method':<20} {'steps/T':>8} {'µs/T':>8} {'max |ΔE/E|':>10} "
            f"{'E 10–10²':>9} {'E last dec.':>11} {'|q| − 1':>8}"
        )
        print(head)
        print("-" * len(head))
        for r in potentials:
            print(
                f"{r['body']:<17} {r['method']:<20} {r['steps_per_period']:>8.0f} "
                f"{r['us_per_period']:>8.1f} {r['energy_max']:>10.1e} "
                f"{r['energy_10_100']:>9.1e} {r['energy_last_decade']:>11.1e} "
                f"{r['quat_norm_drift']:>8.0e}"
            )
    if checks:
        print(
            f"targets on {checks['method']}: "
            + ", ".join(
                f"{k} {v if isinstance(v, bool) else f'{v:.2f}'}"
                for k, v in checks.items()
                if k not in ("method", "baseline", "fine_method")
            )
        )


def plot(rows, path):
    """Log–log energy and |L| errors against time of the torque-free body's rows and, where
    there are rows of potential bodies, their energy errors in a third panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    free = [r for r in rows if r.get("body", "torque-free") == "torque-free"]
    potentials = [r for r in rows if r.get("body", "torque-free") != "torque-free"]
    panels = 3 if potentials else 2
    fig, axes = plt.subplots(1, panels, figsize=(6 * panels, 4.8))
    for r in free:
        style = "--" if r["kind"] == "tsit5" else "-"
        for ax, key in zip(axes, ("energy", "L")):
            x, y = r["curve"][key]
            ax.loglog(x, np.maximum(y, 1e-17), style, label=r["method"])
    colours = {body: f"C{i}" for i, body in enumerate(dict.fromkeys(r["body"] for r in potentials))}
    for r in potentials:  # a colour per body, dashed Tsit5, solid splitting
        style = "--" if r["kind"] == "tsit5" else "-"
        x, y = r["curve"]["energy"]
        axes[2].loglog(
            x,
            np.maximum(y, 1e-17),
            style,
            color=colours[r["body"]],
            label=f"{r['body']}: {r['method']}",
        )
    axes[0].set_title(f"Torque-free body (k² = 0.89, T = {free[0]['period']:.2f}): energy")
    axes[1].set_title("Torque-free body: |L|")
    axes[0].set_ylabel("largest |E/E0 − 1| in each bin")
    axes[1].set_ylabel("largest ||L|/|L0| − 1| in each bin")
    if potentials:
        axes[2].set_title("Under potential torques: energy")
        axes[2].set_ylabel("largest |E/E0 − 1| in each bin")
    for ax in axes:
        ax.set_xlabel("time (periods T of the torque-free body)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def potential_rows(moments, axes, period, periods, per_decade, methods):
    """The long solves of each body of `POTENTIALS` by each of `methods`; their cost per
    period is their wall time over the horizon."""
    rows = []
    for body, torque in POTENTIALS.items():
        model = rb.RigidBody(jnp.asarray(J), torque())
        y0 = rb.State(
            axes @ jnp.asarray(W0_PRINCIPAL),
            rb.rotation.euler_to_quat(jnp.asarray(POTENTIAL_ATTITUDE), "ZXZ"),
        )
        for name in methods:
            t0 = time.perf_counter()
            row = measure(
                name,
                POTENTIAL_METHODS[name],
                model,
                y0,
                moments,
                axes,
                period,
                periods,
                per_decade,
                body,
            )
            row["us_per_period"] = 1e6 * row["wall_s"] / periods
            rows.append(row)
            print(f"  {body}, {name}: {time.perf_counter() - t0:.0f} s", flush=True)
    return rows


def main(
    periods=1e6,
    per_decade=300,
    out="results/benchmarks",
    methods=tuple(METHODS),
    repeats=3,
    potential_periods=1e5,
    potential_methods=tuple(POTENTIAL_METHODS),
):
    model, y0, moments, axes, period = problem()
    rows = []
    for name in methods:
        t0 = time.perf_counter()
        rows.append(
            measure(name, METHODS[name], model, y0, moments, axes, period, periods, per_decade)
        )
        print(f"  {name}: {time.perf_counter() - t0:.0f} s", flush=True)
    cost(rows, model, y0, period, periods, per_decade, repeats)
    potentials = (
        potential_rows(moments, axes, period, potential_periods, per_decade, potential_methods)
        if potential_periods
        else []
    )
    checks = targets(rows, potentials)
    print_table(rows, checks, potentials)
    meta = {
        "periods": periods,
        "potential_periods": potential_periods,
        "per_decade": per_decade,
        "inertia": J.tolist(),
        "omega0_principal": W0_PRINCIPAL.tolist(),
        "period": period,
        "potential_attitude_zxz": list(POTENTIAL_ATTITUDE),
        "global_at_periods": GLOBAL_AT,
        "cost_periods": min(COST_PERIODS, periods),
        "repeats": repeats,
        "targets": checks,
    }
    rows = rows + potentials
    file = _report.write_json(out, "long_horizon", meta, rows)
    plot(rows, file.with_suffix(".png"))
    print(f"wrote {file} and {file.with_suffix('.png')}")
    return rows


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--periods", type=float, default=1e6, help="horizon in periods (1e6)")
    p.add_argument(
        "--potential-periods",
        type=float,
        default=1e5,
        help="horizon of the potential torques' bodies in periods T (1e5; 0: none)",
    )
    p.add_argument("--per-decade", type=int, default=300, help="output times per decade")
    p.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        choices=list(METHODS),
        help="methods to run (default all)",
    )
    p.add_argument("--repeats", type=int, default=3, help="timed rounds (3)")
    p.add_argument("--out", default="results/benchmarks", help="output folder")
    args = p.parse_args()
    main(
        args.periods,
        args.per_decade,
        args.out,
        tuple(args.methods),
        args.repeats,
        args.potential_periods,
    )
