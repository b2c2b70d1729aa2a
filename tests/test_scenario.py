"""Scenarios (rbdyn_jax.scenario): the TOML schema, the registry of torque and frame kinds,
the distributions (samples and centres), the summaries and the solver settings.

The samplers are checked against their distributions (scipy's uniform rotations for
SO(3)), `first_flip_time` against the elliptic solution.
"""

import dataclasses
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from helpers import small_scenario as small
from scipy.spatial.transform import Rotation

import rbdyn_jax as rb
from rbdyn_jax import rotation
from rbdyn_jax.scenario import (
    FRAMES,
    TORQUES,
    AbstractDistribution,
    DispersedInertia,
    EulerAttitude,
    Fixed,
    LogNormal,
    Normal,
    Scenario,
    ScenarioError,
    Uniform,
    UniformSO3,
    _summaries,
    list_scenarios,
)


def minimal(kind: str = "rigid_body", torques=(), frame=None) -> dict:
    """The smallest scenario of `kind` with these torque tables and frame table."""
    d = {
        "model": {"kind": kind, "inertia": {"principal": [1.0, 2.0, 2.5]}},
        "initial": {"omega": [0.1, 1.0, 0.1]},
        "time": {"t1": 1.0, "n": 3},
        "outputs": {"summaries": ["max_abs_omega"]},
    }
    if torques:
        d["model"]["torques"] = list(torques)
    if frame is not None:
        d["model"]["frame"] = frame
    return d


# --------------------------------------------------------------------------------------
# Scenario validation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda d: d["model"].update(colour="red"), "model.colour", "unknown key"),
        (lambda d: d.update(extra=1), "extra", "unknown key"),
        (
            lambda d: d["model"]["inertia"].update(principal="heavy"),
            "model.inertia.principal",
            "list of shape [3]",
        ),
        (
            lambda d: d["model"]["inertia"].update(principal=[1.0, 1.0, 3.0]),
            "model.inertia.principal",
            "A + B ≥ C, docs/physics.md#physical-consistency",
        ),
        (
            lambda d: d["model"]["inertia"].update(principal=[1.0, 2.0]),
            "model.inertia.principal",
            "shape [3]",
        ),
        (lambda d: d["solver"].update(rtol=-1e-8), "solver.rtol", "positive"),
        (lambda d: d["solver"].update(max_steps=10.5), "solver.max_steps", "integer"),
        (lambda d: d["solver"].update(max_steps=10**20), "solver.max_steps", "≤ 2147483647"),
        (lambda d: d["time"].update(t0=-1e308, t1=1e308), "time.t1", "finite span"),
        (
            lambda d: d["model"].update(torques=[{"kind": "restoring_moment", "k": 1, "eps": 2}]),
            "model.torques[0].eps",
            "only with `coeffs`",
        ),
        (lambda d: d["time"].update(n=1), "time.n", "≥ 2"),
        (lambda d: d["time"].update(t1=-1.0), "time.t1", "after t0"),
        (lambda d: d["initial"].update(omega={"dist": "gaussian"}), "initial.omega.dist", "one of"),
        (
            lambda d: d["initial"].update(omega={"dist": "normal", "mean": [0, 1, 0]}),
            "initial.omega.std",
            "missing",
        ),
        (
            lambda d: d["initial"].update(omega={"dist": "normal", "mean": 0, "std": -1}),
            "initial.omega.std",
            "≥ 0",
        ),
        (
            lambda d: d["initial"].update(attitude={"quat": [1.0, 1.0, 0.0, 0.0]}),
            "initial.attitude.quat",
            "unit quaternion",
        ),
        (lambda d: d["outputs"].update(summaries=["max_fun"]), "outputs.summaries", "names from"),
        (
            lambda d: d["model"].update(torques=[{"kind": "magnet"}]),
            "model.torques[0].kind",
            "one of",
        ),
        (
            lambda d: d["model"].update(torques=[{"kind": "body"}]),
            "model.torques[0].moment",
            "missing",
        ),
        (lambda d: d["model"].update(frame={"kind": "inertial"}), "model.frame", "no frame"),
        (
            lambda d: d["outputs"].update(trajectories=0),
            "outputs.trajectories",
            "positive integer K",
        ),
        (
            lambda d: d["outputs"].update(trajectories="some"),
            "outputs.trajectories",
            '"all", "none" or',
        ),
        (lambda d: d["outputs"].update(trajectories=True), "outputs.trajectories", "got True"),
        (lambda d: d["solver"].update(dtype="float16"), "solver.dtype", '"float64" or "float32"'),
        (
            lambda d: d["solver"].update(dtype="float32"),
            "solver.rtol",
            '≥ 9.5e-07 with dtype = "float32"',
        ),  # rtol 1e-9: below float32's rounding
    ],
)
def test_bad_scenarios_name_the_key(edit, key, words):
    d = small()
    edit(d)
    with pytest.raises(ScenarioError) as e:
        Scenario.from_dict(d)
    msg = str(e.value)
    assert f"`{key}`" in msg and words in msg, msg


def test_bad_toml_file_names_the_key(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text(
        '[model]\nkind = "rigid_body"\n[model.inertia]\nprincipal = [1, 2, 2.5]\n'
        "wobble = 3\n[initial]\nomega = [0, 1, 0]\n[time]\nt1 = 1\nn = 3\n"
    )
    with pytest.raises(ScenarioError, match=r"`model\.inertia\.wobble`: unknown key"):
        Scenario.from_toml(f)
    f.write_text("[model\n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        Scenario.from_toml(f)


def test_summary_that_does_not_apply_is_rejected():
    d = small()
    d["model"]["torques"] = [{"kind": "restoring_moment", "coeffs": [1.0, 0.5], "eps": 0.1}]
    with pytest.raises(ScenarioError, match="energy_drift"):
        Scenario.from_dict(d)  # k(τ, ψ) has no potential: no energy integral


@pytest.mark.parametrize("name", list_scenarios())
def test_shipped_scenarios_validate(name):
    sc = Scenario.load(name)
    model, y0 = sc.build(sc.nominal())
    assert isinstance(model, rb.AbstractRigidBody)
    assert sc.ts[0] == sc.t0 and sc.ts[-1] == sc.t1
    assert len(list_scenarios()) >= 5


def test_loading_a_scenario_compiles_no_inertia_program():
    """Every shipped scenario loads with its inertia checked in NumPy: no program of
    rbdyn_jax's inertia (nor an eigenvalue program) is compiled, so a new process, or a
    Dask worker, loads one at once (JAX's staging of arrays aside). In a new process, since
    a program compiled by another test would hide a compilation here."""
    code = (
        "import logging, jax\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "from rbdyn_jax.scenario import Scenario, list_scenarios\n"
        "logs = []\n"
        "class H(logging.Handler):\n"
        "    def emit(self, r): logs.append(r.getMessage())\n"
        "logging.getLogger('jax').addHandler(H())\n"
        "with jax.log_compiles():\n"
        "    jax.jit(lambda x: x + 1)(1.0)  # the logging itself seen\n"
        "    n = len(logs)\n"
        "    for name in list_scenarios():\n"
        "        Scenario.load(name)\n"
        "compiled = [m for m in logs[n:] if m.startswith('Compiling')]\n"
        "print(n > 0, len(compiled) > 0)\n"
        "print([m for m in compiled if any(w in m for w in ('program', 'eigh', 'planar'))])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[:2] == ["True True", "[]"], out.stdout + out.stderr


def test_a_flat_body_is_not_dispersed():
    """A flat body (A + B = C, a zero planar moment) is physical, but has no log-Cholesky
    coordinates to disperse: refused with a positive `log_cholesky_sigma`, taken with 0."""
    d = minimal()
    d["model"]["inertia"] = {"principal": [1.0, 2.0, 3.0], "log_cholesky_sigma": 0.05}
    with pytest.raises(ScenarioError, match="flat body"):
        Scenario.from_dict(d)
    d["model"]["inertia"]["log_cholesky_sigma"] = 0.0
    Scenario.from_dict(d)


# --------------------------------------------------------------------------------------
# The registry of kinds
# --------------------------------------------------------------------------------------

# Minimal tables (without `kind`) of every registered kind, one per way of writing it.
TORQUE_TABLES = {
    "body": [{"moment": [0.0, 0.0, 1e-3]}],
    "inertial": [{"moment": [0.0, 1e-3, 0.0]}],
    "uniform_gravity": [{"weight": 2.0, "com": [0.0, 0.0, 0.1]}],
    "restoring_moment": [{"k": 0.5}, {"coeffs": [1.0, 0.5], "eps": 0.1}],
    "gravity_gradient": [{"eps": 0.01}, {"orbit_rate": 0.1}],
    "balancing_transport": [{}],
}
FRAME_TABLES = {
    "inertial": [{}],
    "constant_rate": [
        {"omega_e": [0.0, 0.0, 0.5]},
        {"omega_e": [0.0, 0.0, 0.5], "quat0": [0.0, 1.0, 0.0, 0.0]},
    ],
    "circular_orbit": [{"n": 0.1}],
    "euler_angles": [
        {},
        {
            "seq": "ZYX",
            "rate": [0.1, 0.0, 0.0],
            "amplitude": 0.1,
            "frequency": {"dist": "uniform", "low": 0.5, "high": 1.0},
        },
    ],
}


@pytest.mark.parametrize("kind", sorted(TORQUES))
def test_every_torque_kind_builds_its_class(kind):
    assert kind in TORQUE_TABLES, f"add a minimal table of the new torque kind {kind!r}"
    spec = TORQUES[kind]
    model_kind = "relative_rigid_body" if spec.relative_only else "rigid_body"
    for table in TORQUE_TABLES[kind]:
        sc = Scenario.from_dict(minimal(model_kind, [{"kind": kind, **table}]))
        model, _ = sc.build(sc.nominal())
        assert sc.torques == (kind,) and type(model.torque) is spec.cls


@pytest.mark.parametrize("kind", sorted(FRAMES))
def test_every_frame_kind_builds_its_class(kind):
    assert kind in FRAME_TABLES, f"add a minimal table of the new frame kind {kind!r}"
    for table in FRAME_TABLES[kind]:
        sc = Scenario.from_dict(minimal("relative_rigid_body", frame={"kind": kind, **table}))
        model, _ = sc.build(sc.nominal())
        assert sc.frame == kind and type(model.frame) is FRAMES[kind].cls
        if "seq" in table:  # a static setting, not a drawn value
            assert model.frame.seq == table["seq"] and "model.frame.seq" not in sc.dists


def test_built_torques_carry_the_drawn_values():
    sc = Scenario.from_dict(
        minimal(
            torques=[
                {
                    "kind": "body",
                    "moment": {"dist": "normal", "mean": [0.0, 0.0, 1e-3], "std": 1e-4},
                },
                {"kind": "gravity_gradient", "orbit_rate": 0.1},
            ]
        )
    )
    values = sc.sample(sc.dists, jax.random.key(0), 3)
    model, _ = sc.build(values)
    body, gg = model.torque.torques
    np.testing.assert_array_equal(body.moment, values["model.torques[0].moment"])
    np.testing.assert_allclose(gg.eps, 3 * 0.1**2, rtol=1e-15)


@pytest.mark.parametrize(
    "model, key, words",
    [
        ({"torques": [{"kind": "magnet"}]}, "model.torques[0].kind", str(sorted(TORQUES))),
        ({"torques": [{"kind": ["body"]}]}, "model.torques[0].kind", "one of"),
        ({"torques": [{"moment": [0, 0, 1]}]}, "model.torques[0].kind", "(missing)"),
        ({"frame": {"kind": "wobbly"}}, "model.frame.kind", str(sorted(FRAMES))),
        ({"frame": {"kind": "inertial", "n": 1.0}}, "model.frame.n", "unknown key"),
        ({"frame": {"kind": "euler_angles", "seq": "ABC"}}, "model.frame.seq", "Euler sequence"),
        ({"frame": {"kind": "circular_orbit"}}, "model.frame.n", "missing"),
        (
            {"torques": [{"kind": "restoring_moment", "k": 1.0, "coeffs": [1.0]}]},
            "model.torques[0]",
            "exactly one of `k` (constant) or `coeffs`",
        ),
        (
            {"torques": [{"kind": "restoring_moment", "coeffs": []}]},
            "model.torques[0].coeffs",
            "non-empty list",
        ),
        (
            {"torques": [{"kind": "gravity_gradient"}]},
            "model.torques[0]",
            "exactly one of `eps` (3μ/R³) or `orbit_rate`",
        ),
        (
            {"torques": [{"kind": "gravity_gradient", "orbit_rate": 0.0}]},
            "model.torques[0].orbit_rate",
            "positive",
        ),
    ],
)
def test_the_schema_refuses_bad_kinds(model, key, words):
    d = minimal("relative_rigid_body")
    d["model"].update(model)
    with pytest.raises(ScenarioError) as e:
        Scenario.from_dict(d)
    msg = str(e.value)
    assert f"`{key}`" in msg and words in msg, msg


def test_a_relative_only_torque_is_refused_on_a_rigid_body():
    with pytest.raises(
        ScenarioError,
        match="`model.torques`: expected balancing_transport "
        'only with kind = "relative_rigid_body"',
    ):
        Scenario.from_dict(minimal(torques=[{"kind": "balancing_transport"}]))


def test_build_refuses_a_kind_the_registry_does_not_hold(monkeypatch):
    """No fallback: a scenario naming a kind that is not registered (edited after
    validation, or taken out of the registry since) fails to build."""
    sc = Scenario.from_dict(minimal(torques=[{"kind": "body", "moment": [0.0, 0.0, 1.0]}]))
    bad = dataclasses.replace(sc, torques=("magnet",))
    with pytest.raises(ScenarioError, match=r"`model\.torques\[0\]\.kind`.*'magnet'"):
        bad.build(bad.nominal())
    rel = Scenario.from_dict(minimal("relative_rigid_body", frame={"kind": "inertial"}))
    with pytest.raises(ScenarioError, match=r"`model\.frame\.kind`.*'wobbly'"):
        dataclasses.replace(rel, frame="wobbly").build(rel.nominal())
    monkeypatch.delitem(TORQUES, "body")
    with pytest.raises(ScenarioError, match="'body'"):
        sc.build(sc.nominal())


# --------------------------------------------------------------------------------------
# Distributions: centres, samplers
# --------------------------------------------------------------------------------------


def test_each_distribution_centre():
    """Mean, mid-point, median, fixed value, nominal inertia, the attitude of the centre
    angles, and the identity for a uniform attitude."""
    a, b = jnp.array([1.0, -2.0, 0.5]), jnp.array([3.0, 4.0, 1.5])
    J = jnp.array([[2.0, 0.1, 0.0], [0.1, 3.0, -0.2], [0.0, -0.2, 4.0]])
    cases = [
        (Fixed(a), a),
        (Normal(a, b), a),
        (Uniform(a, b), 0.5 * (a + b)),
        (LogNormal(b, jnp.full(3, 0.1)), b),
        (DispersedInertia(J, jnp.asarray(0.05)), J),
        (EulerAttitude(Uniform(a, b), "ZXZ"), rotation.euler_to_quat(0.5 * (a + b), "ZXZ")),
        (UniformSO3(), jnp.array([1.0, 0.0, 0.0, 0.0])),
    ]
    assert {type(d) for d, _ in cases} == set(AbstractDistribution.__subclasses__())
    for dist, want in cases:
        np.testing.assert_array_equal(dist.centre(), want, err_msg=type(dist).__name__)
    sc = Scenario.from_dict(small())
    nominal = sc.nominal()
    np.testing.assert_array_equal(nominal["initial.omega"], [0.1, 1.0, 0.1])
    np.testing.assert_array_equal(nominal["model.inertia"], np.diag([1.0, 2.0, 2.5]))


def draws(sc: Scenario, n: int, seed: int = 0) -> dict:
    idx = jnp.arange(n)
    return jax.jit(jax.vmap(lambda i: sc.sample(sc.dists, jax.random.key(seed), i)))(idx)


@pytest.mark.parametrize(
    "euler",
    [
        {"dist": "normal", "mean": [10.0, 40.0, -20.0], "std": 5.0},
        {"dist": "uniform", "low": [0.0, 10.0, 20.0], "high": 30.0},
        {"dist": "lognormal", "median": [10.0, 40.0, 20.0], "sigma": 0.5},
    ],
    ids=["normal", "uniform", "lognormal"],
)
def test_euler_angles_in_degrees_draw_the_attitudes_of_the_same_angles_in_radians(euler):
    """`degrees = true` converts the angles (means, spreads, bounds, medians), not a
    log-normal's σ, which is a spread of log(angle) and has no unit."""
    deg = np.pi / 180.0
    rad = {
        k: v if k in ("dist", "sigma") else (np.asarray(v) * deg).tolist() for k, v in euler.items()
    }
    attitude = {k: small() for k in ("deg", "rad")}
    attitude["deg"]["initial"]["attitude"] = {"euler": euler, "degrees": True}
    attitude["rad"]["initial"]["attitude"] = {"euler": rad}
    q = {k: draws(Scenario.from_dict(d), 64)["initial.attitude"] for k, d in attitude.items()}
    # the same angles up to the rounding of the conversion (a few ulps of an angle ≤ 1 rad)
    np.testing.assert_allclose(q["deg"], q["rad"], rtol=0, atol=1e-14)
    assert float(jnp.std(q["rad"][:, 0])) > 0.01  # the draws spread


def test_uniform_so3_matches_scipy_random_rotations():
    """The rotation angle of a Haar-uniform rotation has density (1 − cos a)/π; compare
    with scipy's `Rotation.random` by a two-sample KS test, and E[R] = 0."""
    q = np.asarray(draws(Scenario.from_dict(small()), 4000)["initial.attitude"])
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-14) and np.all(q[:, 0] >= 0)
    angle = 2 * np.arccos(np.clip(q[:, 0], -1, 1))
    ref = Rotation.random(4000, random_state=1).magnitude()
    assert scipy.stats.ks_2samp(angle, ref).pvalue > 1e-3
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    assert np.abs(R.mean(0)).max() < 5 / np.sqrt(4000)  # E[R] = 0, |R_ij| ≤ 1


def test_dispersed_inertia_is_physical_with_the_asked_spread():
    d = small()
    d["model"]["inertia"] = {
        "matrix": [[2.0, 0.1, 0.0], [0.1, 3.0, -0.2], [0.0, -0.2, 4.0]],
        "log_cholesky_sigma": 0.05,
    }
    J = np.asarray(draws(Scenario.from_dict(d), 2000)["model.inertia"])
    assert bool(np.all(rb.inertia.is_physical(jnp.asarray(J))))
    assert np.all(np.linalg.eigvalsh(J) > 0) and np.allclose(J, np.swapaxes(J, -1, -2))
    # planar moments of J' = L Lᵀ: log L_ii ~ N(log L_ii⁰, σ²) exactly
    theta = np.asarray(jax.vmap(rb.inertia.to_log_cholesky)(jnp.asarray(J)))
    assert np.allclose(theta[:, :3].std(0), 0.05, rtol=0.1)  # 2000 draws: ±3 % (1σ)
    assert np.allclose(np.median(J, axis=0), d["model"]["inertia"]["matrix"], atol=0.05)


def test_normal_uniform_lognormal_moments_and_independent_keys():
    d = small()
    d["initial"]["omega"] = {"dist": "lognormal", "median": [1.0, 2.0, 3.0], "sigma": 0.1}
    d["model"]["torques"] = [
        {"kind": "body", "moment": {"dist": "uniform", "low": -1.0, "high": [1.0, 2.0, 3.0]}}
    ]
    d["outputs"]["summaries"] = ["max_abs_omega"]  # a body torque has no potential energy
    x = draws(Scenario.from_dict(d), 4000)
    w, m = np.asarray(x["initial.omega"]), np.asarray(x["model.torques[0].moment"])
    assert np.allclose(np.median(w, 0), [1, 2, 3], rtol=0.01)  # ± ~0.4 % (1σ)
    assert np.allclose(np.log(w).std(0), 0.1, rtol=0.05)
    assert np.all(m >= -1) and np.all(m < [1, 2, 3])
    assert np.allclose(m.mean(0), [0, 0.5, 1.0], atol=0.06)  # σ/√n ≈ 0.02–0.03
    # adding a random quantity does not change the draws of the others (path-keyed)
    before = draws(Scenario.from_dict(small()), 50)
    after = draws(Scenario.from_dict(d), 50)
    assert np.array_equal(before["model.inertia"], after["model.inertia"])
    assert np.array_equal(before["initial.attitude"], after["initial.attitude"])


# --------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------


def test_first_flip_time_against_the_elliptic_solution():
    """Intermediate-axis spin: the first zero of ω₂ in the Jacobi elliptic solution."""
    J = np.array([1.0, 2.0, 2.5])
    w0 = jnp.array([0.05, 1.0, 0.02])
    ts = jnp.linspace(0.0, 30.0, 3001)
    w = np.asarray(rb.analytic.torque_free_elliptic(jnp.asarray(J), w0, ts))
    k = np.argmax(np.sign(w[1:, 1]) != np.sign(w[0, 1]))
    fine = np.linspace(float(ts[k]), float(ts[k + 1]), 1001)
    wf = np.asarray(rb.analytic.torque_free_elliptic(jnp.asarray(J), w0, jnp.asarray(fine)))
    t_true = fine[np.argmax(np.sign(wf[:, 1]) != np.sign(wf[0, 1]))]
    coarse = ts[::10]
    got = _summaries._first_flip(coarse, jnp.asarray(w[::10]), jnp.diag(jnp.asarray(J)))
    # linear interpolation over Δt = 0.1 where ω₂ is nearly linear: error ≪ Δt
    assert abs(float(got) - t_true) < 2e-3
    never = _summaries._first_flip(coarse[:5], jnp.asarray(w[:50:10]), jnp.diag(jnp.asarray(J)))
    assert np.isnan(float(never))


# --------------------------------------------------------------------------------------
# Solver settings
# --------------------------------------------------------------------------------------


def test_solver_table_gives_the_diffrax_objects():
    d = minimal()
    d["solver"] = {"method": "Dopri5", "rtol": 1e-7, "atol": 1e-9, "max_steps": 100}
    sc = Scenario.from_dict(d)
    assert isinstance(sc.diffrax_solver, diffrax.Dopri5) and sc.max_steps == 100
    c = sc.stepsize_controller
    assert isinstance(c, diffrax.PIDController) and (c.rtol, c.atol) == (1e-7, 1e-9)
    default = Scenario.from_dict(minimal())
    assert isinstance(default.diffrax_solver, diffrax.Tsit5)
    d["solver"]["method"] = "Euler"
    with pytest.raises(ScenarioError, match="`solver.method`: expected one of"):
        Scenario.from_dict(d)


def test_a_float32_scenario_is_float32_throughout():
    """`[solver] dtype = "float32"`: the times, every distribution's arrays, the draws and
    the built models are float32 (so JAX computes in float32 with 64-bit types on), and the
    tolerances default to 1e-6, the power of ten above float32's finest rtol."""
    d = small(solver={"dtype": "float32"})
    d["model"]["torques"] = [{"kind": "gravity_gradient", "eps": 0.01}]
    d["outputs"]["summaries"] = ["max_abs_omega"]
    sc = Scenario.from_dict(d)
    assert (sc.dtype, sc.rtol, sc.atol, sc.ts.dtype) == ("float32", 1e-6, 1e-6, np.float32)
    leaves = jax.tree_util.tree_leaves(sc.dists)
    assert leaves and all(x.dtype == jnp.float32 for x in leaves)
    values = sc.sample(sc.dists, jax.random.key(0), 3)
    assert all(v.dtype == jnp.float32 for v in values.values())
    built = jax.tree_util.tree_leaves(sc.build(values))
    assert all(x.dtype == jnp.float32 for x in built if jnp.issubdtype(x.dtype, jnp.floating))
    assert sc.nominal()["initial.attitude"].dtype == jnp.float32


def test_with_settings_sets_the_dtype_and_the_states_kept():
    sc = Scenario.load("torque_free_flip")
    assert sc.with_settings() is sc and sc.with_settings(trajectories="all") is sc
    sampled = sc.with_settings(trajectories=5)
    assert (sampled.trajectories, sampled.name) == (5, "torque_free_flip")
    assert (
        sampled.source["outputs"]["trajectories"] == 5
        and "trajectories" not in sc.source["outputs"]
    )  # the source holds what the scenario runs with
    with pytest.raises(ScenarioError) as e:  # the shipped rtol, 1e-8, is finer than float32
        sc.with_settings(dtype="float32")
    assert "`solver.rtol`" in str(e.value) and "9.5e-07" in str(e.value)
    assert 'dtype = "float32"' in str(e.value) and "got 1e-08" in str(e.value)
    d = sc.source
    d["solver"].update(rtol=1e-6, atol=1e-6)
    single = Scenario.from_dict(d).with_settings(dtype="float32")
    assert single.dtype == "float32" and single.source["solver"]["dtype"] == "float32"


def test_a_scenario_is_a_pytree_of_its_distributions_leaves():
    """A `Scenario` flattens to its distributions' arrays; its structure is static and one
    for sources that differ only in naming a default `dtype` or `trajectories` (a sweep's
    stores keeping all, some or no states run one chunk program), and differs where a
    setting differs."""
    sc = Scenario.load("torque_free_flip")
    leaves, treedef = jax.tree_util.tree_flatten(sc)
    assert leaves and all(isinstance(x, jax.Array) for x in leaves)
    assert len(leaves) == len(jax.tree_util.tree_leaves(sc.dists))
    again = jax.tree_util.tree_unflatten(treedef, [x + 0 for x in leaves])
    assert again.source == sc.source and again.name == sc.name and again.ts.shape == sc.ts.shape
    back = sc.with_settings(trajectories="none").with_settings(trajectories="all")
    assert back.source != sc.source  # names the default now
    assert jax.tree_util.tree_structure(back) == treedef
    assert jax.tree_util.tree_structure(sc.with_settings(dtype="float64")) == treedef
    d = dict(sc.source)  # a copy: "solver" replaced below, not changed
    d["solver"] = {**d.get("solver", {}), "rtol": 1e-6, "atol": 1e-6}
    loose = Scenario.from_dict(d)
    for other in (
        sc.with_settings(trajectories="none"),
        loose,
        loose.with_settings(dtype="float32"),
    ):
        assert jax.tree_util.tree_structure(other) != treedef
