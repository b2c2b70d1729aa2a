"""`rbdyn fit`: identify the inertia and/or torque parameters from an observation file
(`identify.Observations.from_file`), print them with their standard errors, write fit.json and
fit.png, and say what to try when the fit did not converge."""

import sys
import time

from ._common import EXIT_NOT_CONVERGED, EXIT_USAGE, compilation_cache


class _Refused(Exception):
    """A user's error in the command's input: `rbdyn fit: MESSAGE`, status 2."""


def fit_command(args) -> int:
    """`rbdyn fit DATA --model SCENARIO`: 0 for a converged fit, `EXIT_NOT_CONVERGED` (its
    files written) or a user's error."""
    import pathlib

    written = [pathlib.Path(args.out) / f for f in ("fit.json", "fit.png")]
    kept = [str(f) for f in written if f.exists()]
    if kept and not args.overwrite:  # before the fit: nothing replaced unasked
        print(
            f"rbdyn fit: {' and '.join(kept)} already there: pass --overwrite to replace "
            "them, or choose another --out",
            file=sys.stderr,
        )
        return EXIT_USAGE
    import jax

    jax.config.update("jax_enable_x64", True)
    compilation_cache(jax)
    from .. import identify

    try:
        scenario, model = _model(args.model)
        try:
            data = identify.Observations.from_file(
                args.data,
                sigma_omega=args.sigma_omega,
                sigma_quat=args.sigma_quat,
                trajectories=args.trajectories,
                seq=args.seq,
                normalize_quat=args.normalize_quat,
            )
            params, where = free_params(
                [s.strip() for s in args.free.split(",") if s.strip()], model.torque
            )
        except (ValueError, OSError) as e:  # the option's name where the library's is said
            raise _Refused(str(e).replace("`normalize_quat=True`", "--normalize-quat")) from e
        scale = scale_arg(args.scale)
        K, n = data.ts.shape
        print(
            f"rbdyn fit: {K} trajectories × {n} samples from {args.data}; model "
            f"{scenario.name} ({', '.join(scenario.torques) or 'no torque'}); free: "
            f"{', '.join(params)}"
        )
        horizons = _horizons_arg(args.horizons)
        t0 = time.perf_counter()
        try:
            with compile_meter(jax) as meter:
                res = identify.fit(
                    model,
                    data,
                    params=params,
                    torque_where=where,
                    scale=scale,
                    optimizer=identify.LevenbergMarquardt(steps=args.steps),
                    horizons=None if horizons == (1.0,) else horizons,
                )
        except ValueError as e:
            raise _Refused(e) from e
    except _Refused as e:
        print(f"rbdyn fit: {e}", file=sys.stderr)
        return EXIT_USAGE
    elapsed = time.perf_counter() - t0
    _print_progress(args.steps, horizons, res, time_text(elapsed, meter))
    report = {
        "converged": bool(res.converged),
        "loss": float(res.loss),
        "notes": list(res.notes),
        "time_s": elapsed,
        **_print_values(res, params),
    }
    for note in res.notes:
        print(f"  note: {note}")
    import json

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.json").write_text(json.dumps(report, indent=2))
    if _plot(out / "fit.png", data, res):
        print(f"wrote {out / 'fit.json'} and {out / 'fit.png'}")
    else:
        print(f"wrote {out / 'fit.json'} (no plot: pip install matplotlib)")
    return _verdict(args, res, horizons, params, K)


def _model(name: str):
    """`--model`: the scenario and its model at the nominal values (the initial guess)."""
    from ..models import RigidBody
    from ..scenario import Scenario, ScenarioError

    try:
        scenario = Scenario.load(name)
    except ScenarioError as e:
        raise _Refused(f"invalid scenario: {e}") from e
    model, _ = scenario.build(scenario.nominal())
    if not isinstance(model, RigidBody):
        raise _Refused("only rigid_body scenarios can be fitted (absolute motion).")
    return scenario, model


def scale_arg(text: str | None):
    """`--scale`: `trace=V` → `identify.TraceScale(V)`, `moment=AXIS:V` →
    `identify.MomentScale(AXIS, V)`; none given → `None` (the scale not fixed)."""
    if not text:
        return None
    from .. import identify

    kind, _, value = text.partition("=")
    axis, _, v = value.partition(":")
    try:
        if kind == "trace":
            return identify.TraceScale(float(value))
        if kind.startswith("moment"):
            return identify.MomentScale(int(axis), float(v))
        raise ValueError(f"unknown {kind!r}")
    except ValueError as e:  # a bad number, or a scale identify refuses
        raise _Refused(f"--scale is trace=V or moment=AXIS:V ({e})") from e


def _horizons_arg(text: str) -> tuple[float, ...]:
    """`--horizons`: a comma list of fractions."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise _Refused("--horizons is a comma list such as 0.25,0.5,1") from None


def _print_progress(steps: int, horizons, res, took: str) -> None:
    """The line on how the loss went, in how many steps and how long."""
    import numpy as np

    lh = np.asarray(res.loss_history)
    if horizons == (1.0,):
        print(
            f"  loss {lh[0]:.6g} → {lh[-1]:.6g} in at most {steps} step"
            f"{'s' if steps > 1 else ''}, converged: {res.converged}, {took}"
        )
    else:
        print(
            f"  horizons {', '.join(f'{h:g}' for h in horizons)} of each record, at most "
            f"{steps} step{'s' if steps > 1 else ''} each: loss {lh[-1]:.6g} over "
            f"the whole record, converged: {res.converged}, {took}"
        )


def _print_values(res, params) -> dict:
    """Print the fitted inertia and torque parameters with their standard errors; return
    them for fit.json."""
    import jax
    import numpy as np

    report = {}
    if "inertia" in params:
        J = np.asarray(res.model.inertia)
        se = np.asarray(res.stderr["inertia"])
        print("  inertia J ± stderr:")
        for i in range(3):
            print("    " + "  ".join(f"{J[i, j]:+.6f} ± {se[i, j]:.2e}" for j in range(3)))
        report.update(inertia=J.tolist(), inertia_stderr=se.tolist())
    if "torque" in params:
        rows = []
        for path, se in jax.tree_util.tree_leaves_with_path(res.stderr["torque"]):
            name = jax.tree_util.keystr(path)
            val = np.atleast_1d(np.asarray(_get_path(res.model.torque, path)))
            se = np.atleast_1d(np.asarray(se))
            for i in range(val.size):
                rows.append((f"{name}[{i}]" if val.size > 1 else name, val.flat[i], se.flat[i]))
        print("  torque parameters ± stderr:")
        for name, v, e in rows:
            print(f"    torque{name:24s} {v:+.6g} ± {e:.2e}")
        report["torque"] = {f"torque{r[0]}": [float(r[1]), float(r[2])] for r in rows}
    return report


def _plot(path, data, res) -> bool:
    """fit.png: the observed samples (dots) against the fitted trajectories, of the first
    four records; `False` (nothing written) without matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return False
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ..integrate import simulate

    show = min(data.num_trajectories, 4)
    fig = Figure(figsize=(11, 3.0 * show), layout="constrained")
    axes = fig.subplots(show, 2, squeeze=False)
    for k in range(show):
        m = np.asarray(data.mask[k])
        ts = np.asarray(data.ts[k])
        y0 = jax.tree_util.tree_map(lambda x, k=k: x[k], res.y0)
        traj = simulate(res.model, y0, jnp.asarray(ts), throw=False)
        if data.omega is not None:
            ax = axes[k, 0]
            for c in range(3):
                ax.plot(ts[m], np.asarray(data.omega[k])[m, c], ".", ms=3, color=f"C{c}")
                ax.plot(
                    ts, np.asarray(traj.ys.omega)[:, c], "-", color=f"C{c}", label=f"ω_{'xyz'[c]}"
                )
            ax.set(
                xlabel="t [s]",
                ylabel="ω [rad/s]",
                title=f"trajectory {k}: ω observed (dots) vs fitted",
            )
            ax.legend(fontsize=7)
        if data.quat is not None:
            ax = axes[k, 1]
            qs, qo = np.asarray(traj.ys.quat), np.asarray(data.quat[k])
            qo = np.where(np.sum(qs * qo, -1, keepdims=True) < 0, -qo, qo)  # same sign
            for c in range(4):
                ax.plot(ts[m], qo[m, c], ".", ms=3, color=f"C{c}")
                ax.plot(ts, qs[:, c], "-", color=f"C{c}", label="q_" + "wxyz"[c])
            ax.set(
                xlabel="t [s]",
                ylabel="quaternion",
                title=f"trajectory {k}: attitude observed (dots) vs fitted",
            )
            ax.legend(fontsize=7)
    if not res.converged:
        fig.suptitle("not converged: the fitted curves are where the fit stopped", color="C3")
    fig.savefig(path, dpi=90)
    return True


def free_params(names: list[str], torque):
    """`--free` names → (`params`, `torque_where`) for `identify.fit`: `inertia`,
    `initial_conditions` (or `ic`), `torque` (every array leaf of the torque), `k` (the
    restoring moments' k, or their K(τ) coefficients)."""
    from ..torques import RestoringMoment, SumTorque

    params, where = [], None
    for name in names:
        if name == "inertia":
            params.append("inertia")
        elif name in ("initial_conditions", "ic"):
            params.append("initial_conditions")
        elif name in ("torque", "k"):
            if "torque" not in params:
                params.append("torque")
        else:
            raise ValueError(f"--free: unknown {name!r}; expected inertia, k, torque, ic")
    if "k" in names and "torque" not in names:
        parts = list(torque.torques) if isinstance(torque, SumTorque) else [torque]
        picks = [i for i, t in enumerate(parts) if isinstance(t, RestoringMoment)]
        if not picks:
            raise ValueError("--free k: the scenario's model has no restoring_moment torque")

        def leaf(t):
            return t.k.coeffs if callable(t.k) else t.k

        if isinstance(torque, SumTorque):
            where = lambda tq: tuple(leaf(tq.torques[i]) for i in picks)  # noqa: E731
        else:
            where = leaf
    return tuple(params), where


def _get_path(obj, path):
    for key in path:
        obj = getattr(obj, key.name) if hasattr(key, "name") else obj[key.idx]
    return obj


def compile_meter(jax):
    """A context in which JAX's own reports are counted: `tracing_s`, the seconds spent
    tracing, lowering and compiling programs in this process (a program loaded from JAX's
    persistent cache is not compiled: its time is not counted), and `loaded`, the programs
    loaded from the caches (JAX's persistent cache, rbdyn_jax's traced programs)."""
    import contextlib

    from .._program import traces

    meter = {"tracing_s": 0.0, "loaded": 0, "hit": False}
    work = (
        "/jax/core/compile/jaxpr_trace_duration",
        "/jax/core/compile/jaxpr_to_mlir_module_duration",
    )

    def event(name, **_):
        if name == "/jax/compilation_cache/cache_hits":  # inside the compile event below
            meter["loaded"] += 1
            meter["hit"] = True

    def duration(name, seconds, **_):
        if name == "/jax/core/compile/backend_compile_duration":
            if not meter["hit"]:
                meter["tracing_s"] += seconds
            meter["hit"] = False
        elif name in work:
            meter["tracing_s"] += seconds

    @contextlib.contextmanager
    def metering():
        hits = traces.stats["hits"]
        jax.monitoring.register_event_listener(event)
        jax.monitoring.register_event_duration_secs_listener(duration)
        try:
            yield meter
        finally:
            jax.monitoring.unregister_event_listener(event)
            jax.monitoring.unregister_event_duration_listener(duration)
            meter["loaded"] += traces.stats["hits"] - hits

    return metering()


def time_text(elapsed: float, meter: dict) -> str:
    """`4.7 s (3.9 s of it tracing and compiling)`, `0.5 s (program loaded from the cache)`:
    what the fit's time held, as `compile_meter` measured it."""
    parts = []
    if meter["loaded"]:
        parts.append("program loaded from the cache")
    if meter["tracing_s"] >= 0.5:  # not the small programs around a loaded one
        parts.append(f"{meter['tracing_s']:.1f} s of it tracing and compiling")
    return f"{elapsed:.1f} s" + (f" ({', '.join(parts)})" if parts else "")


def _finer(horizons: tuple[float, ...]) -> str:
    """More, shorter stages than `horizons`: half the first, and a stage between each two."""
    h = [horizons[0] / 2, horizons[0]]
    for a, b in zip(horizons, horizons[1:]):
        h += [(a + b) / 2, b]
    return ",".join(f"{x:g}" for x in h)


def _hints(args, res, horizons, params, K) -> list[str]:
    """What to try after a fit that did not converge, for what its result shows."""
    import numpy as np

    loss, decrement = float(res.loss), float(res.decrement)
    hints = []
    if not np.isfinite(loss):
        hints.append(
            "the model could not be solved at the starting point (the loss is not "
            "finite): start nearer the truth (see the last point)"
        )
    elif decrement >= 1e-2 * loss:  # Gauss–Newton: a step would still lower the loss much
        hints.append(
            f"the loss ({loss:.4g}) is still falling (a Gauss–Newton step would "
            f"lower it by up to {decrement:.3g}): more steps, --steps "
            f"{max(2 * args.steps, 30)}"
        )
    else:
        hints.append(
            f"the loss stalled at {loss:.4g} (a further step would lower it by at "
            f"most {decrement:.3g}), a local minimum that more steps do not leave"
        )
    if horizons == (1.0,):
        hints.append(
            "fit growing parts of the records, each stage starting from the last: "
            "--horizons 0.25,0.5,1 (a long or chaotic record fitted whole stalls in a "
            "local minimum)"
        )
    else:
        hints.append(
            f"start from a shorter part of the records, in more stages: --horizons "
            f"{_finer(horizons)}"
        )
    if "inertia" in params and args.scale is None and not res.scale_identified:
        hints.append(
            "the data fix J only up to scale: fix it with --scale trace=V or --scale moment=AXIS:V"
        )
    if res.ill_determined > (0 if res.scale_identified and args.scale is None else 1):
        hints.append(
            f"{res.ill_determined} direction(s) of the parameters are ill-determined: "
            "free fewer of them (--free), or fit more data"
        )
    if args.trajectories is not None:
        hints.append(
            f"fit more records, if the data hold more than the {K} fitted: "
            f"--trajectories {2 * K}, or leave --trajectories out for all of them"
        )
    hints.append(
        f"start nearer the truth: the fit starts from the nominal values of the "
        f"[model] of {args.model} and the first observed states; give --model a "
        "scenario file whose [model] values are closer (`rbdyn scenarios` names the "
        "shipped files to copy)"
    )
    return hints


def _verdict(args, res, horizons, params, K) -> int:
    """0 for a converged fit; else `EXIT_NOT_CONVERGED`, with what to try on stderr."""
    if res.converged:
        return 0
    print(
        "rbdyn fit: the fit did not converge: the values above are where it stopped, not a "
        "fit of the data. To try:",
        file=sys.stderr,
    )
    for hint in _hints(args, res, horizons, params, K):
        print(f"  - {hint}", file=sys.stderr)
    return EXIT_NOT_CONVERGED
