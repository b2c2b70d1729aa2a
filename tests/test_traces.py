"""The on-disk cache of traced programs (`rbdyn_jax/_program/traces.py`): a later process gets the
same results from a loaded trace as from tracing, and a key never lets one call's program
serve another's."""

import json
import os
import subprocess
import sys
import textwrap

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import host_callbacks

import rbdyn_jax as rb
from rbdyn_jax._program import traces as _traces
from rbdyn_jax._program.xla import QUICK_COMPILE_OPTIONS
from rbdyn_jax.integrate import _simulate

J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
TS = np.linspace(0.0, 5.0, 11)


def solve_args(model=None, y0=None, ts=TS, solver=None, max_steps=4096, rtol=1e-8):
    """The arguments `simulate` hands its compiled solve."""
    model = rb.RigidBody(J) if model is None else model
    y0 = rb.State(jnp.array([0.3, -1.0, 0.5]), jnp.array([1.0, 0, 0, 0])) if y0 is None else y0
    ts, controller, max_steps, dt0 = _simulate._prepare(model, y0, ts, None, rtol, 1e-8, max_steps)
    return (
        model,
        y0,
        ts,
        diffrax.Tsit5() if solver is None else solver,
        controller,
        diffrax.RecursiveCheckpointAdjoint(),
        max_steps,
        dt0,
    )


def test_key_is_the_same_for_new_values_and_differs_for_a_new_program():
    base = _traces.key("solve", solve_args())
    assert base is not None
    # Values are inputs of the program, not part of it: the same key.
    assert _traces.key("solve", solve_args(model=rb.RigidBody(J * 2.0))) == base
    assert _traces.key("solve", solve_args(rtol=1e-6)) == base
    assert _traces.key("solve", solve_args(ts=TS + 1.0)) == base
    # Anything the trace reads changes the key.
    other = [
        solve_args(max_steps=4097),  # a static int
        solve_args(solver=diffrax.Dopri5()),  # another solver class
        solve_args(ts=np.linspace(0.0, 5.0, 12)),  # a shape
        solve_args(model=rb.RigidBody(J, rb.UniformGravity(1.0, jnp.array([0.0, 0, 0.5])))),
        solve_args(
            y0=rb.State(jnp.array([0.3, -1.0, 0.5], jnp.float32), jnp.array([1.0, 0, 0, 0]))
        ),  # a dtype
    ]
    keys = [_traces.key("solve", a) for a in other]
    assert None not in keys
    assert len(set(keys) | {base}) == len(other) + 1
    assert _traces.key("another function", solve_args()) != base


class UsersTorque(rb.torques.AbstractTorque):
    """A torque class from outside rbdyn_jax: its code is versioned by nothing the key
    holds, so a model using it must never be cached."""

    c: jax.Array

    def __call__(self, t, kin, inertia):
        return -self.c * kin.omega


def test_key_refuses_what_it_cannot_describe():
    model = rb.RigidBody(J, UsersTorque(jnp.asarray(0.1)))
    assert _traces.key("solve", solve_args(model=model)) is None
    scale = 2.0
    assert _traces.key("f", (lambda x: scale * x,)) is None  # a test module's function
    assert _traces.key("f", (object(),)) is None  # an object known only by its address
    # the libraries' own classes and functions are described by name
    assert (
        _traces.key(
            "f",
            (
                diffrax.PIDController,
                jnp.float64,
                rb.inertia.principal_axes,
                diffrax.RESULTS.successful,
            ),
        )
        is not None
    )
    # a numpy array is an input (its values are not in the key); a static one (an
    # equinox static field) is described by its content
    assert _traces.key("f", (np.arange(3.0),)) == _traces.key("f", (np.arange(3.0) + 1,))
    assert _traces._value(np.arange(3.0)) != _traces._value(np.arange(3.0) + 1)


def test_memo_follows_the_full_key():
    """The per-process memo returns what the full description gives, and a static float
    or int of the same value but another type is another key."""
    args = solve_args()
    leaves, treedef = jax.tree_util.tree_flatten(args)
    assert _traces._memo_key("solve", treedef, leaves) == _traces.key("solve", args)
    one_int = _traces._memo_key("f", *reversed(jax.tree_util.tree_flatten((1,))))
    one_float = _traces._memo_key("f", *reversed(jax.tree_util.tree_flatten((1.0,))))
    assert one_int != one_float


SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] != "none":
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    import jax.numpy as jnp, numpy as np
    import rbdyn_jax as rb
    from rbdyn_jax._program import traces as _traces
    J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
    w = np.random.default_rng(1).normal(size=(12, 3)) * np.linspace(0.05, 3, 12)[:, None]
    w = jnp.asarray(w)
    y0s = rb.State(w, jnp.tile(jnp.array([1.0, 0, 0, 0]), (12, 1)))
    ts = np.linspace(0.0, 5.0, 11)
    one = rb.simulate(rb.RigidBody(J), rb.State(w[0], y0s.quat[0]), ts)
    plain = rb.simulate_batch(rb.RigidBody(J), y0s, ts, batching=rb.Vmap())
    # 4 of 12 fail:
    lanes = rb.simulate_batch(rb.RigidBody(J), y0s, ts, batching=rb.Lanes(4), max_steps=50)
    out = {}
    for name, tr in (("one", one), ("plain", plain), ("lanes", lanes)):
        for i, leaf in enumerate(jax.tree_util.tree_leaves(tr)):
            out[f"{name}{i}"] = np.asarray(leaf)
    # A stored program's outputs are free to move, as `jit`'s are: they mix with the lane
    # solve's, which lives on every device.
    assert not any(x.committed for x in jax.tree_util.tree_leaves(one))
    out["mixed"] = np.asarray(lanes.ys.omega[0] - one.ys.omega)
    np.savez(sys.argv[2], **out)
    print(json.dumps(_traces.stats))
""")


def _run(cache, tmp_path, script=SCRIPT, **env):
    """`script` in a fresh process: this process's use of the trace cache (and what else
    the script prints), and the arrays it saved."""
    text, script, out = script, tmp_path / "traced.py", tmp_path / "out.npz"
    script.write_text(text)
    # One XLA device unless asked: this process's XLA_FLAGS may ask for more (benchmarks/
    # gradients.py sets two on import, `import rbdyn_jax` one per core unless
    # RBDYN_JAX_CONFIGURE_XLA=0), and the device count is in every key.
    base = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1")
    proc = subprocess.run(
        [sys.executable, str(script), str(cache), str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(base, **env),
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), dict(np.load(out))


def _stored_then_loaded(tmp_path, script, stores, hits):
    """`script` in three fresh processes, no cache, an empty one, the same one again: the
    second stores `stores` traces and the third loads `hits` (and stores none); every saved
    array bitwise the same in all three. The arrays of the first."""
    cache = tmp_path / "cache"
    runs = [_run(c, tmp_path, script=script) for c in ("none", cache, cache)]
    assert [stats for stats, _ in runs] == [
        {"hits": 0, "stores": 0, "uncacheable": 0},
        {"hits": 0, "stores": stores, "uncacheable": 0},
        {"hits": hits, "stores": 0, "uncacheable": 0},
    ]
    ref = runs[0][1]
    for _, out in runs[1:]:
        assert_same(out, ref)
    return ref


def assert_same(a, b):
    """Bitwise the same leaves (NaN where the other has NaN)."""
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k, strict=True)


def test_a_later_process_loads_the_traces_and_gets_the_same_results(tmp_path):
    """Fresh processes with JAX's cache configured: an empty cache (the three solves are
    traced and stored); the same cache (all three loaded, none traced); the same cache with
    the trace cache turned off (`RBDYN_JAX_TRACE_CACHE=0`: nothing loaded or stored, the
    solves traced as without a cache). Every result bitwise equal (the same program),
    including the per-trajectory failure codes of the lane solve. Then two XLA devices, over
    which the lane solve splits its batch: stored and loaded in the same way, with the same
    results."""
    cache = tmp_path / "cache"
    cold_stats, cold = _run(cache, tmp_path)
    warm_stats, warm = _run(cache, tmp_path)
    ref_stats, ref = _run(cache, tmp_path, RBDYN_JAX_TRACE_CACHE="0")
    assert cold_stats == {"hits": 0, "stores": 3, "uncacheable": 0}
    assert warm_stats == {"hits": 3, "stores": 0, "uncacheable": 0}
    assert ref_stats == {"hits": 0, "stores": 0, "uncacheable": 0}
    assert len(list((cache / "rbdyn_jax-traces").glob("*.jaxexport"))) == 3
    assert_same(cold, ref)
    assert_same(warm, ref)
    codes = ref["lanes7"]  # `result` of the lane solve: max_steps reached for some
    assert (codes == 0).any() and (codes == rb.RESULTS.max_steps_reached._value).any()
    # Two devices: the device count is in every key (nothing loaded at first); the lane
    # solve, split over both, is stored and loaded like the others.
    two = dict(XLA_FLAGS="--xla_force_host_platform_device_count=2")
    two_stats, two_cold = _run(cache, tmp_path, **two)
    assert two_stats == {"hits": 0, "stores": 3, "uncacheable": 0}
    two_stats, two_warm = _run(cache, tmp_path, **two)
    assert two_stats == {"hits": 3, "stores": 0, "uncacheable": 0}
    assert_same(two_warm, two_cold)
    for k in ref:  # the same trajectories as on one device, to round-off
        np.testing.assert_allclose(two_cold[k], ref[k], rtol=0, atol=1e-12, err_msg=k)


def test_a_truncated_entry_is_traced_used_and_stored_anew(tmp_path, monkeypatch):
    """An entry cut short (a full disk, say) is not loaded: the call traces its program,
    gets the same result, and stores the entry anew, which is then loaded as any other."""
    monkeypatch.setattr(_traces, "directory", lambda: tmp_path)

    def fn(x, scale):
        return jnp.sin(x) * scale

    fn.__module__ = "rbdyn_jax.integrate"  # describable, as rbdyn_jax's own solves are
    x = jnp.array([1.5, 2.0])
    want = np.asarray(jax.jit(fn)(x, 3.0))  # traced as without the cache

    def fresh_process_call():
        """The call as a later process makes it: nothing loaded in this one yet."""
        monkeypatch.setattr(_traces, "_LOADED", {})
        before = dict(_traces.stats)
        np.testing.assert_array_equal(_traces.cached(fn)(x, 3.0), want, strict=True)
        return {k: _traces.stats[k] - before[k] for k in before}

    assert fresh_process_call() == {"hits": 0, "stores": 1, "uncacheable": 0}
    (entry,) = tmp_path.glob("*.jaxexport")
    assert fresh_process_call() == {"hits": 1, "stores": 0, "uncacheable": 0}
    entry.write_bytes(entry.read_bytes()[:100])
    assert fresh_process_call() == {"hits": 0, "stores": 1, "uncacheable": 0}
    assert fresh_process_call() == {"hits": 1, "stores": 0, "uncacheable": 0}
    assert len(entry.read_bytes()) > 100


def test_a_program_export_refuses_is_traced_as_without_the_cache(tmp_path, monkeypatch):
    """`jax.export` refuses a program with a host callback: the call then goes through its
    plain jit (same result), is counted uncacheable, nothing is stored, and the export is
    not tried again."""
    monkeypatch.setattr(_traces, "directory", lambda: tmp_path)
    tries, export = [], _traces.export

    def counted(f):
        tries.append(f)
        return export(f)

    monkeypatch.setattr(_traces, "export", counted)
    seen = []

    def fn(x, scale):
        jax.debug.callback(lambda v: seen.append(float(v)), x[0])
        return x * scale

    fn.__module__ = "rbdyn_jax.integrate"  # describable, as rbdyn_jax's own solves are
    call = _traces.cached(fn)
    before = dict(_traces.stats)
    x = jnp.array([1.5, 2.0])
    for _ in range(2):
        np.testing.assert_array_equal(call(x, 3.0), x * 3.0)
    assert _traces.stats["uncacheable"] - before["uncacheable"] == 2
    assert _traces.stats["stores"] == before["stores"]
    assert not list(tmp_path.iterdir())
    assert seen == [1.5, 1.5]  # each call ran the plain jit, callback included
    assert len(tries) == 1


CALLER = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] != "none":
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    import jax.numpy as jnp, numpy as np
    import rbdyn_jax as rb
    from rbdyn_jax._program import traces as _traces
    from rbdyn_jax.integrate import _batching
    traced = []  # the lane loops traced in this process
    loop = _batching.lane_loop
    _batching.lane_loop = lambda *a, **k: traced.append(1) or loop(*a, **k)
    J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
    w = jnp.asarray(np.random.default_rng(1).normal(size=(6, 3)))
    y0s = rb.State(w, jnp.tile(jnp.array([1.0, 0, 0, 0]), (6, 1)))
    ts = np.linspace(0.0, 3.0, 5)
    def loss(theta, scale):
        model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
        tr = rb.simulate_batch(model, y0s, ts, batching=rb.Lanes(2))
        return jnp.sum(jnp.sin(tr.ys.omega * scale) ** 2) + jnp.sum(tr.ys.quat[..., 1:] ** 2)
    th, one, two = rb.inertia.to_log_cholesky(J) + 0.05, 1.0, jnp.array([1.0, 0.5])
    out = {"grad": jax.jit(jax.grad(loss))(th, one),
           "jacfwd": jax.jit(jax.jacfwd(loss))(th, one)}
    loops = len(traced)  # the caller's own programs so far: nothing else traced a loop
    out["vmap_grad"] = jax.jit(jax.vmap(jax.grad(loss), in_axes=(None, 0)))(th, two)
    out["hessian"] = jax.jit(jax.hessian(loss))(th, one)
    np.savez(sys.argv[2], **{k: np.asarray(v) for k, v in out.items()})
    print(json.dumps(dict(_traces.stats, loops=loops)))
""")


def test_a_callers_gradient_holds_the_stored_loops_and_gets_the_same_results(tmp_path):
    """A caller's own `jit(grad)`, `jit(jacfwd)`, `jit(vmap(grad))` and `jit(hessian)` of a
    loss through the lane solver, in three fresh processes: no cache; an empty cache (the
    forward loop and the sensitivities' two loops, of ω's group and of the whole state,
    are stored: `integrate._dependencies.closed_groups`); the same cache (all three loaded, and the
    gradients trace no lane loop at all). The vmap and the Hessian transform the
    stored loops through `fn`'s own rules (`embedded`'s fallbacks). Every result bitwise
    equal (the stored program is the traced one), but the Hessian's: its fallback wraps
    `fn`'s jvp in another program structure, which XLA may fuse and round differently
    (seen: 1 ulp), so it is compared to 1e-13 of its largest element."""
    cache = tmp_path / "cache"
    ref_stats, ref = _run("none", tmp_path, script=CALLER)
    cold_stats, cold = _run(cache, tmp_path, script=CALLER)
    warm_stats, warm = _run(cache, tmp_path, script=CALLER)
    assert ref_stats == {"hits": 0, "stores": 0, "uncacheable": 0, "loops": 3}
    assert cold_stats == {"hits": 0, "stores": 3, "uncacheable": 0, "loops": 3}
    assert warm_stats == {"hits": 3, "stores": 0, "uncacheable": 0, "loops": 0}
    for out in (cold, warm):
        np.testing.assert_allclose(
            out.pop("hessian"),
            ref["hessian"],
            rtol=1e-13,
            atol=1e-13 * np.abs(ref["hessian"]).max(),
        )
    assert_same(cold, {k: v for k, v in ref.items() if k != "hessian"})
    assert_same(warm, cold)
    assert np.all(np.isfinite(ref["hessian"]))
    np.testing.assert_allclose(ref["hessian"], ref["hessian"].T, rtol=1e-9, atol=1e-12)


FIT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] != "none":
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    import jax.numpy as jnp, numpy as np
    import rbdyn_jax as rb
    from rbdyn_jax import identify
    from rbdyn_jax._program import traces as _traces
    J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
    model = rb.RigidBody(J, rb.UniformGravity(2.0, jnp.array([0.0, 0.0, 0.1])))
    w = jnp.asarray(np.random.default_rng(2).normal(size=(2, 3)))
    y0s = rb.State(w, jnp.tile(jnp.array([1.0, 0, 0, 0]), (2, 1)))
    ts = np.linspace(0.0, 2.0, 9)
    truth = rb.simulate_batch(model, y0s, ts, rtol=1e-10, atol=1e-10)
    data = identify.Observations(ts, omega=truth.ys.omega, quat=truth.ys.quat)
    guess = rb.RigidBody(1.1 * jnp.diag(jnp.diag(J)), model.torque)
    res = identify.fit(guess, data, optimizer=identify.LevenbergMarquardt(steps=4))
    leaves = jax.tree_util.tree_leaves((res.model, res.y0, res.loss_history, res.covariance,
                                        res.stderr))
    np.savez(sys.argv[2], **{f"fit{i}": np.asarray(x) for i, x in enumerate(leaves)})
    print(json.dumps(_traces.stats))
""")


def test_a_later_process_loads_the_fit_and_gets_the_same_result(tmp_path):
    """`identify.fit`'s whole program (its Levenberg–Marquardt loop) in three fresh
    processes: no cache; an empty cache (the fit and the solve making the data stored);
    the same cache (both loaded, nothing traced). The fitted model, initial states, loss
    history, covariance and standard errors bitwise equal in all three."""
    ref = _stored_then_loaded(tmp_path, FIT, stores=2, hits=2)
    assert np.all(np.isfinite(ref["fit0"]))


SWEEP = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    if sys.argv[1] != "none":
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    import numpy as np, xarray as xr
    from rbdyn_jax import sweep
    from rbdyn_jax._program import traces as _traces
    out = sys.argv[2] + ".zarr"
    sweep.run("torque_free_flip", 96, out, chunk=64, lanes=4, overwrite=True)
    ds = xr.open_zarr(out)
    np.savez(sys.argv[2], **{k: ds[k].values for k in ds.data_vars})
    print(json.dumps(_traces.stats))
""")


def test_a_later_process_loads_the_sweep_program_and_writes_the_same_store(tmp_path):
    """`sweep.run` in three fresh processes: no cache; an empty cache (the chunk program is
    stored, and the lane loop inside it); the same cache (the chunk program loaded: nothing
    traced, not even the loop). Every variable of the store bitwise equal."""
    ref = _stored_then_loaded(tmp_path, SWEEP, stores=2, hits=1)
    assert (ref["status"] == 0).all() and np.isfinite(ref["omega"]).all()


def test_key_holds_the_compiler_options():
    """A program stored for other XLA options is another entry: it is compiled with them."""
    args = solve_args()
    quick = _traces.key("solve", args, QUICK_COMPILE_OPTIONS)
    assert quick not in (None, _traces.key("solve", args))
    leaves, treedef = jax.tree_util.tree_flatten(args)
    assert _traces._memo_key("solve", treedef, leaves, QUICK_COMPILE_OPTIONS) == quick
    assert _traces._memo_key("solve", treedef, leaves) == _traces.key("solve", args)


def test_memo_tells_signed_zeros_apart():
    """0.0 == -0.0 in Python, but a trace may hold either: the memo keys floats by repr."""
    keys = [
        _traces._memo_key("f", *reversed(jax.tree_util.tree_flatten((z,)))) for z in (0.0, -0.0)
    ]
    assert keys[0] != keys[1]
    assert keys == [_traces.key("f", (0.0,)), _traces.key("f", (-0.0,))]


def test_numpy_inputs_inside_a_callers_trace_are_checked_now_not_at_run_time():
    """NumPy `ts` and inertia inside a caller's `jit` stay concrete: they are checked while
    tracing, and the caller's program holds no host callback (it can be cached). A traced
    inertia still gets its runtime check, and so does a NumPy one that fails the check
    (the error is raised by the caller's program, as before); bad `ts` raise at once."""
    q = jnp.tile(jnp.array([1.0, 0, 0, 0]), (3, 1))

    def omegas(w, Jm=np.asarray(J)):
        # One device: a check that fails in a program over several devices aborts the
        # process (`rb.Lanes`).
        traj = rb.simulate_batch(
            rb.RigidBody(Jm), rb.State(w, q), TS, batching=rb.Lanes(2, devices=1)
        )
        return traj.ys.omega

    w = jnp.ones((3, 3))
    assert host_callbacks(jax.make_jaxpr(omegas)(w).jaxpr) == []
    assert host_callbacks(jax.make_jaxpr(omegas)(w, J).jaxpr) != []  # a traced inertia
    bad = np.diag([1.0, 1.0, 3.0])  # violates the triangle inequality
    with pytest.raises(Exception, match="inertia"):
        jax.block_until_ready(jax.jit(lambda w: omegas(w, bad))(w))
    ts_bad = TS[::-1]
    with pytest.raises(ValueError, match="increasing"):
        jax.make_jaxpr(
            lambda w: rb.simulate_batch(
                rb.RigidBody(J), rb.State(w, q), ts_bad, batching=rb.Lanes(2)
            )
        )(w)
