"""Where a lane gradient's time goes, per Runge–Kutta step: the forward step against the
step of each way of differentiating it.

The lane solver's gradient (`simulate_batch(..., batching=rb.Lanes(…))` under `jax.grad` or
`jax.jacfwd`) integrates forward sensitivities by the solve's own steps
(`integrate._sensitivity.Sensitivity`). `gradients.py` times whole solves; this script
times one Tsit5
step as the lane loop takes it (diffrax's `solver.step` on the lanes' batched state,
`integrate._lane_system.LaneField`: the lane axis last on every leaf of the state, of the
sensitivities and of a per-lane model, the lanes' times of shape `(lanes,)`, NumPy's rank
promotion allowed around the step), for

- `forward`: the state (ω, q), the step of the forward solve;
- `sensitivities`: the state and ω's 18 columns for the six inertia parameters, the step of
  `gradients.py`'s ω loss under `jax.grad` (`_Sensitivity`, as `_lane_jvp` builds it);
- `sensitivities, field zeroed`: the same 25 components carried, the columns' rates set to
  zero: what carrying them costs;
- `sensitivities, no parameter part`: the columns' rates ∂f/∂y·S without ∂f/∂p (wrong
  values, timed only): what the parameter part of their field costs;
- `reverse, diffrax VJP (scan_kind=…)`: one step of a discrete adjoint (a reverse pass over
  recorded steps): ω's step recomputed from the recorded ω (ω's group is closed for a
  torque-free body) and the adjoint λ pulled back through it by `jax.vjp` of diffrax's step,
  the per-lane inertia cotangent accumulated. Reverse mode needs diffrax's `bounded` or
  `checkpointed` stage loop. What such a pass would pay per step, before its recording and
  its own lane bookkeeping.

Each is a compiled `fori_loop` of `--steps` steps of fixed size; the table gives the
minimum over `--rounds` interleaved rounds, per step and as a multiple of the forward step.
Check: after the steps, the reverse loop's inertia cotangent equals the sensitivities
contracted with the same λ (both are the derivative of the same discrete steps); the
relative difference is printed and saved.

Setting: `gradients.py`'s body (J with products of inertia) and ω0 ~ N(0, 1) per axis
(`default_rng(0)`) on `--lanes` lanes (default 16, as `gradients.py`), identity attitude,
Tsit5, float64, steps of 0.005 in the unit time of a 20 s solve (the cost of a step does
not depend on its size). XLA as docs/performance.md advises (`rb.configure_xla()`: its while loops
compiled whole), one device: the steps of one device's loop, each loop compiled with
`rb.COMPILER_OPTIONS` as rbdyn_jax compiles its own.

Run: `python benchmarks/gradient_steps.py [--lanes 16] [--steps 300] [--rounds 20]
[--out DIR]` — prints a table and writes DIR/gradient_steps.json (DIR defaults to
results/benchmarks).
"""

import rbdyn_jax as rb  # JAX starts XLA at its first computation, after this

if __name__ == "__main__":  # a script: before JAX starts (imported by a test: as is)
    rb.configure_xla()

import argparse  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from rbdyn_jax import _compat  # noqa: E402  (the term the lane loop hands its solver)
from rbdyn_jax.integrate._lane_system import LaneField, Plain  # noqa: E402
from rbdyn_jax.integrate._sensitivity import SYMMETRIC, Sensitivity  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import _report  # noqa: E402

J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
SPAN, H = 20.0, 0.005  # a 20 s solve in unit time (as `gradients.py`'s); the step in it
P = 6  # the inertia's six parameters (`integrate._sensitivity.unit_columns`)


class _ZeroField(Sensitivity):
    """The columns carried, their rates zero."""

    def vector_field(self, t, ys, args):
        y, S = ys
        return self.model.vector_field(t, y, args), tuple(jnp.zeros_like(s) for s in S)


class _OmegaGroup(eqx.Module):
    """ω's rate alone, the attitude held: ω's closed group for a torque-free body."""

    model: rb.RigidBody
    quat: jax.Array

    def vector_field(self, t, w, args):
        return self.model.vector_field(t, rb.State(w, self.quat), args).omega


def _jit(fn):
    """`jax.jit` with the options rbdyn_jax compiles its own programs with
    (`rbdyn_jax/_program/xla.py`)."""
    return jax.jit(fn, compiler_options=rb.COMPILER_OPTIONS)


def _loops(lanes, steps, kind_list):
    """name -> a function of no arguments running its compiled loop; and the check."""
    model = rb.RigidBody(jnp.asarray(J))
    # The lane axis last on every leaf (`LaneField`): ω (3, lanes), q (4, lanes); each
    # lane's ω0 as before the layout changed (the rows of a (lanes, 3) draw).
    w0 = jnp.asarray(np.random.default_rng(0).normal(size=(lanes, 3)).T)
    y0 = rb.State(w0, jnp.tile(jnp.array([[1.0], [0.0], [0.0], [0.0]]), (1, lanes)))
    t0, span = jnp.asarray(0.0), jnp.asarray(SPAN)
    tprev = jnp.zeros(lanes)  # the lanes' times, (lanes,) as the lane loop's
    tnext = tprev + H
    ok = jnp.ones(lanes, bool)
    solver = diffrax.Tsit5(scan_kind="lax")  # the lane loop's stage loop
    # The model's one array leaf is its inertia (`which`); ω is the state's first leaf
    # (`carried`): the columns `lane_jvp` integrates for a loss on ω.
    assert len(jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))) == 1
    args = ((0,), (0,), P, (True,), (0,))

    def stepper(field_model, y0):
        term = _compat.wrapped_term(diffrax.ODETerm(LaneField(field_model, False, t0, span)))
        f0 = term.vf(tprev, y0, ok)  # the FSAL state, as the lane loop starts it

        def body(_, c):
            y, ss = c
            # (lanes,) times against (…, lanes) leaves, as `lane_loop`'s step allows
            with jax.numpy_rank_promotion("allow"):
                y1, _, _, ss1, _ = solver.step(term, tprev, tnext, y, ok, ss, False)
            return y1, ss1

        return jax.lax.fori_loop(0, steps, body, (y0, (jnp.array(False), f0)))[0]

    S0 = (jnp.zeros((3 * P, lanes)),)  # ω's (3, P) columns per lane, flattened
    fns = {"forward": _jit(lambda y0: stepper(Plain(model), y0))}
    for name, aug in (
        ("sensitivities", Sensitivity(model, *args)),
        ("sensitivities, field zeroed", _ZeroField(model, *args)),
        # no parameter leaf differentiated: ∂f/∂y·S alone, the same P columns
        ("sensitivities, no parameter part", Sensitivity(model, (), (), P, (), (0,))),
    ):
        fns[name] = _jit(lambda y0, aug=aug: stepper(aug, (y0, S0)))

    # The reverse pass: per-lane inertia (a batched model, (3, 3, lanes)), ω recorded at
    # each step start.
    Jl = jnp.broadcast_to(jnp.asarray(J)[..., None], (3, 3, lanes))
    group = eqx.tree_at(lambda g: g.model.inertia, _OmegaGroup(model, y0.quat), Jl)

    def omega_step(kind):
        rk = diffrax.Tsit5(scan_kind=kind)

        def step(w, Jl):
            g = eqx.tree_at(lambda g: g.model.inertia, group, Jl)
            term = _compat.wrapped_term(diffrax.ODETerm(LaneField(g, True, t0, span)))
            f0 = term.vf(tprev, w, ok)
            with jax.numpy_rank_promotion("allow"):
                return rk.step(term, tprev, tnext, w, ok, (jnp.array(False), f0), False)[0]

        return step

    def record(w0):
        step = omega_step("lax")

        def body(k, c):
            w, ws = c
            return step(w, Jl), ws.at[k].set(w)

        return jax.lax.fori_loop(0, steps, body, (w0, jnp.zeros((steps,) + w0.shape)))[1]

    def reverse(kind):
        step = omega_step(kind)

        def run(ws, lam):
            def body(k, c):
                lam, mu = c
                with jax.numpy_rank_promotion("allow"):
                    _, vjp = jax.vjp(step, ws[steps - 1 - k], Jl)
                    dw, dJ = vjp(lam)
                return dw, mu + dJ

            return jax.lax.fori_loop(0, steps, body, (lam, jnp.zeros_like(Jl)))

        run = _jit(run)
        return lambda: run(ws, lam)

    ws = _jit(record)(w0)
    lam = jnp.asarray(np.random.default_rng(1).normal(size=(lanes, 3)).T)  # (3, lanes)
    calls = {name: (lambda f=f: f(y0)) for name, f in fns.items()}
    for kind in kind_list:
        calls[f"reverse, diffrax VJP (scan_kind={kind})"] = reverse(kind)

    def check():
        """max |g_sens − g_rev| / max |g_sens| of d(λ·ω_K)/dθ over the six parameters."""
        S = calls["sensitivities"]()[1][0].reshape(3, P, lanes)
        g_sens = jnp.einsum("ipl,il->pl", S, lam)
        dJ = calls[f"reverse, diffrax VJP (scan_kind={kind_list[0]})"]()[1]  # (3, 3, lanes)
        g_rev = jnp.stack([dJ[i, i] if i == j else dJ[i, j] + dJ[j, i] for i, j in SYMMETRIC])
        return float(jnp.max(jnp.abs(g_sens - g_rev)) / jnp.max(jnp.abs(g_sens)))

    return calls, check


def main(
    lanes=16, steps=300, rounds=20, kinds=("bounded", "checkpointed"), out="results/benchmarks"
):
    calls, check = _loops(lanes, steps, kinds)
    first = {}
    for name, call in calls.items():
        t = time.perf_counter()
        jax.block_until_ready(call())
        first[name] = time.perf_counter() - t
    times = {name: [] for name in calls}
    for _ in range(rounds):  # interleaved: every loop once per round
        for name, call in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(call())
            times[name].append(time.perf_counter() - t)
    unit = min(times["forward"]) / steps
    rows = [
        {
            "method": name,
            "first_call_s": first[name],
            "us_per_step": min(ts) / steps * 1e6,
            "x_forward_step": min(ts) / steps / unit,
            "median_us_per_step": float(np.median(ts)) / steps * 1e6,
        }
        for name, ts in times.items()
    ]
    error = check()
    width = max(len(r["method"]) for r in rows)
    print(f"{lanes} lanes, {steps} Tsit5 steps, minimum of {rounds} interleaved rounds")
    print(f"{'method':<{width}} | first call s | µs / step | × forward step | median µs")
    print("-" * (width + 58))
    for r in rows:
        print(
            f"{r['method']:<{width}} | {r['first_call_s']:12.2f} | {r['us_per_step']:9.2f} "
            f"| {r['x_forward_step']:14.2f} | {r['median_us_per_step']:9.2f}"
        )
    print(f"reverse vs sensitivities, d(λ·ω_K)/dθ: relative difference {error:.1e}")
    meta = {
        "lanes": lanes,
        "steps": steps,
        "rounds": rounds,
        "step": H,
        "span": SPAN,
        "solver": "Tsit5",
        "reverse_vs_sensitivities": error,
    }
    print("wrote", _report.write_json(out, "gradient_steps", meta, rows))
    return rows, error


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lanes", type=int, default=16)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=20)
    ap.add_argument("--out", default="results/benchmarks")
    a = ap.parse_args()
    main(a.lanes, a.steps, a.rounds, out=a.out)
