"""float32 solves, with `jax_enable_x64` off as a float32 user runs (a fresh process: the
suite turns float64 on), against the float64 solves of this process.

Checked: `simulate_batch` (both layouts of the lane loop, and `Vmap`) and `simulate` run in
float32, take the float32 default tolerance (1e-6: 1e-8 is finer than float32 resolves) and
refuse a finer `rtol` with a message; their trajectories agree with float64 ones at the
same tolerances to what float32 rounding adds (bounds below, measured first); and
`identify.fit` recovers an inertia in float32.
"""

import json
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import equations

import rbdyn_jax as rb
from rbdyn_jax.integrate import default_tolerance, min_rtol

HIGHEST = jax.lax.Precision.HIGHEST
J = np.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
N, T_END, N_OUT = 32, 20.0, 21

CHILD = textwrap.dedent(f"""
    import json
    import jax, jax.numpy as jnp, numpy as np
    import rbdyn_jax as rb
    from rbdyn_jax import identify
    assert not jax.config.jax_enable_x64
    J = jnp.asarray({J.tolist()!r})
    w = jnp.asarray(np.random.default_rng(0).normal(size=({N}, 3)))
    y0s = rb.State(w, jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), ({N}, 1)))
    ts = jnp.linspace(0.0, {T_END}, {N_OUT})
    out = {{"dtype": str(ts.dtype)}}
    for name, batching in (("cpu", rb.Lanes(8, layout="cpu")),
                           ("array", rb.Lanes(8, layout="array")), ("vmap", rb.Vmap())):
        tr = rb.simulate_batch(rb.RigidBody(J), y0s, ts, batching=batching)
        out[name] = {{"omega": np.asarray(tr.ys.omega).tolist(),
                     "dtype": str(tr.ys.omega.dtype),
                     "ok": bool(jnp.all(tr.result == rb.RESULTS.successful)),
                     "steps": np.asarray(tr.stats["num_steps"]).tolist()}}
    one = rb.simulate(rb.RigidBody(J), rb.State(w[0], y0s.quat[0]), ts)
    out["simulate"] = np.asarray(one.ys.omega).tolist()
    try:
        rb.simulate_batch(rb.RigidBody(J), y0s, ts, rtol=1e-8)
    except ValueError as e:
        out["refused"] = str(e)
    top = rb.UniformGravity(weight=1.0, com=jnp.array([0.0, 0.0, 0.2]))
    obs_ts = jnp.linspace(0.0, 4.0, 41)
    y0 = rb.State(jnp.array([0.3, -0.2, 1.5]), jnp.array([1.0, 0.1, 0.0, 0.0]))
    observed = rb.simulate(rb.RigidBody(J, top), y0, obs_ts).ys
    fit = identify.fit(rb.RigidBody(jnp.diag(jnp.array([2.2, 2.8, 4.1])), top),
                       identify.Observations(obs_ts, omega=observed.omega[None],
                                             quat=observed.quat[None],
                                             sigma_omega=1e-4, sigma_quat=1e-4),
                       optimizer=identify.LevenbergMarquardt(steps=60))
    out["fit"] = {{"inertia": np.asarray(fit.model.inertia).tolist(),
                  "dtype": str(fit.model.inertia.dtype)}}
    print(json.dumps(out))
""")


# The tests reading the child's run share one worker (`--dist loadgroup`): it runs once.
SHARES_THE_CHILD = pytest.mark.xdist_group("float32_child")


@pytest.fixture(scope="module")
def child():
    run = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.splitlines()[-1])


def test_default_tolerance_and_the_finest_rtol_follow_the_dtype():
    assert min_rtol(np.float32) == pytest.approx(9.5367e-07, rel=1e-4)
    assert min_rtol(np.float64) == pytest.approx(1.7764e-15, rel=1e-4)
    assert default_tolerance(np.float64) == 1e-8
    assert default_tolerance(np.float32) == pytest.approx(1e-6)
    assert default_tolerance(np.float32, 1e-4) == 1e-4
    # float32 inputs with float64 on: the solve is float32 and refuses a finer rtol too
    y0s = rb.State(
        jnp.ones((2, 3), jnp.float32), jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (2, 1))
    )
    model = rb.RigidBody(jnp.asarray(J, jnp.float32))
    ts = jnp.linspace(0.0, 1.0, 3, dtype=jnp.float32)
    with pytest.raises(ValueError, match=r"`rtol` = 1e-07 is finer than float32 resolves"):
        rb.simulate_batch(model, y0s, ts, rtol=1e-7)
    tr = rb.simulate_batch(model, y0s, ts)
    assert tr.ys.omega.dtype == jnp.float32
    # float64 times and model make it a float64 solve, where 1e-10 is fine
    tr = rb.simulate_batch(
        rb.RigidBody(jnp.asarray(J)), y0s, ts.astype(jnp.float64), rtol=1e-10, atol=1e-10
    )
    assert tr.ys.omega.dtype == jnp.float64


@SHARES_THE_CHILD
def test_float32_solves_with_x64_off(child):
    """Against float64 at rtol = atol = 1e-6 (the float32 default): both are 1e-6-accurate
    solves per unit of time; float32 adds its rounding (ε = 1.2e-7 per operation, growing
    over ~300 steps and through the error control). Measured: ≤ 3e-4 over 20 s on O(1)
    rates, a median of ~1e-5; the bounds below have margin, and a float64 constant or a
    wrong cast inside the float32 path would not change them, but a wrong step would."""
    assert child["dtype"] == "float32"
    assert "finer than float32 resolves" in child["refused"]
    w = np.random.default_rng(0).normal(size=(N, 3))
    y0s = rb.State(jnp.asarray(w), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (N, 1)))
    ts = jnp.linspace(0.0, T_END, N_OUT)
    ref = rb.simulate_batch(rb.RigidBody(jnp.asarray(J)), y0s, ts, rtol=1e-6, atol=1e-6)
    ref_steps = np.asarray(ref.stats["num_steps"])
    for name in ("cpu", "array", "vmap"):
        got = child[name]
        assert got["dtype"] == "float32" and got["ok"], name
        err = np.max(np.abs(np.asarray(got["omega"]) - np.asarray(ref.ys.omega)), axis=(1, 2))
        assert np.max(err) < 3e-3 and np.median(err) < 1e-4, (name, err)
        # the step control sees rounding near the tolerance: a few steps more or less
        assert np.all(np.abs(np.asarray(got["steps"]) - ref_steps) <= 0.1 * ref_steps + 3)
    np.testing.assert_allclose(child["simulate"], child["vmap"]["omega"][0], rtol=0, atol=1e-5)


@SHARES_THE_CHILD
def test_identification_in_float32(child):
    """`identify.fit` with x64 off: float32 solves at its default tolerance (1e-10, raised
    to 1e-6 in float32) recover the inertia of a heavy top from noise-free rates and
    attitude (σ = 1e-4 assumed for both) to about 1e-4 of its size, against 1e-9 in
    float64. The attitude matters in float32: from the rates alone the inertia's scale is
    ill-determined, and Levenberg–Marquardt's path then depends on rounding (from six
    initial guesses about half stall at errors of 1e-2 to 1, and which half changes with the
    solve's round-off). With the attitude all six reach ≤ 2e-4 after 60 steps (measured):
    the bound of 2e-3 leaves a factor of 10."""
    assert child["fit"]["dtype"] == "float32"
    np.testing.assert_allclose(child["fit"]["inertia"], J, rtol=0, atol=2e-3)


def test_the_suite_runs_in_float64():
    assert jax.config.jax_enable_x64


def full_precision(jaxpr) -> tuple[int, list]:
    """The number of `dot_general`s in a jaxpr (and its sub-jaxprs), and those of them not
    asking for full precision."""
    dots = [e for e in equations(jaxpr) if e.primitive.name == "dot_general"]
    return len(dots), [e for e in dots if e.params["precision"] != (HIGHEST, HIGHEST)]


def test_matrix_products_ask_for_full_precision(monkeypatch):
    """At JAX's default precision NVIDIA GPUs multiply float32 matrices in TF32 (~1e-3
    relative), which a float32 solve at 1e-6 cannot afford: every matrix product rbdyn_jax
    writes as one asks for full precision (on a CPU, or in float64, the same program).
    Checked on the inertia, invariants and rotation functions, and on the whole program of
    `identify.fit` (its normal equations and covariance), traced as `fit` calls it."""
    J32 = jnp.asarray(np.diag([1.0, 2.0, 3.0]), jnp.float32)
    w = jnp.ones((5, 3), jnp.float32)
    tr = rb.Trajectory(
        ts=jnp.zeros(5, jnp.float32),
        ys=rb.State(w, jnp.tile(jnp.array([1.0, 0, 0, 0], jnp.float32), (5, 1))),
        stats={},
        result=rb.RESULTS.successful,
    )
    for fn, args in [
        (rb.inertia.kinetic_energy, (J32, w)),
        (rb.inertia.moment_about, (J32, w[0])),
        (rb.inertia.from_principal, (jnp.ones(3, jnp.float32),)),
        (rb.inertia.from_log_cholesky, (jnp.zeros(6, jnp.float32),)),
        (lambda m, t: rb.invariants.energy(m, t), (rb.RigidBody(J32), tr)),
        (lambda m, t: rb.invariants.angular_momentum_inertial(m, t), (rb.RigidBody(J32), tr)),
        (rb.rotation.dcm_derivative, (jnp.eye(3, dtype=jnp.float32), w[0])),
    ]:
        count, default = full_precision(jax.make_jaxpr(fn)(*args))
        assert count and not default, fn
    from rbdyn_jax import identify
    from rbdyn_jax.identify import _fit

    traced = []
    run = _fit.run

    def recording(*args):
        traced.append(eqx.filter_make_jaxpr(run.fn)(*args)[0])
        return run(*args)

    monkeypatch.setattr(_fit, "run", recording)
    ts = jnp.linspace(0.0, 1.0, 6)
    y0 = rb.State(jnp.array([0.3, -0.2, 1.5]), jnp.array([1.0, 0.0, 0.0, 0.0]))
    observed = rb.simulate(rb.RigidBody(jnp.asarray(J)), y0, ts).ys.omega
    identify.fit(
        rb.RigidBody(jnp.asarray(J) * 1.1),
        identify.Observations(ts, omega=observed[None], sigma_omega=1e-3),
        optimizer=identify.LevenbergMarquardt(steps=2),
    )
    count, default = full_precision(traced[0])
    assert count and not default
