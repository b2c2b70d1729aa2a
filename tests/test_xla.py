"""`_program.xla`: every program rbdyn_jax compiles gets `COMPILER_OPTIONS` when it is compiled at
the top level, and stays callable inside a caller's transformations (JAX refuses compiler
options on a nested jit); `configure_xla` sets XLA's flags, and a process started with them
compiles every loop whole and gets the same trajectories and gradients. `import rbdyn_jax`
sets them itself (one device per core), never over the user's flags, and not with
`RBDYN_JAX_CONFIGURE_XLA=0`."""

import ast
import json
import os
import pathlib
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rbdyn_jax as rb
from rbdyn_jax._program import flags as _xla_flags, xla as _xla

PACKAGE = pathlib.Path(rb.__file__).parent


def test_top_level_is_false_under_every_transformation():
    seen = []

    def probe(x):
        seen.append(_xla.top_level())
        return x

    for transform in (jax.jit, jax.vmap, jax.grad, jax.jacfwd, eqx.filter_jit):
        seen.clear()
        transform(probe)(jnp.ones(()) if transform is not jax.vmap else jnp.ones(2))
        assert seen == [False], transform
    assert _xla.top_level()


@pytest.mark.parametrize("jitter", [_xla.jit, _xla.filter_jit])
def test_wrapped_function_runs_alike_at_top_level_and_nested(jitter):
    f = jitter(lambda x: jnp.sin(x) * x)
    x = jnp.linspace(0.1, 1.0, 4)
    want = np.sin(np.asarray(x)) * np.asarray(x)
    np.testing.assert_allclose(f(x), want, rtol=1e-15)  # own program, with the options
    np.testing.assert_allclose(jax.jit(f)(x), want, rtol=1e-15)  # nested: a plain jit
    np.testing.assert_allclose(jax.vmap(f)(x), want, rtol=1e-15)
    np.testing.assert_allclose(
        jax.grad(lambda x: jnp.sum(f(x)))(x),
        np.sin(np.asarray(x)) + np.asarray(x) * np.cos(np.asarray(x)),
        rtol=1e-14,
    )


def test_a_nested_jit_with_options_is_what_jax_0_10_refuses():
    """Why `_xla` dispatches: JAX 0.10 refuses a nested jit with compiler options; 0.11
    takes it. The dispatch can go with JAX 0.10."""
    g = jax.jit(jnp.sin, compiler_options=_xla.COMPILER_OPTIONS)
    assert float(g(1.0)) == pytest.approx(np.sin(1.0))
    nested = jax.jit(lambda x: g(x))
    if jax.__version_info__ < (0, 11):
        with pytest.raises(ValueError, match="top-level"):
            nested(1.0)
    else:
        assert float(nested(1.0)) == pytest.approx(np.sin(1.0))


@pytest.mark.parametrize("options", [rb.COMPILER_OPTIONS, _xla.QUICK_COMPILE_OPTIONS])
def test_the_options_are_known_to_this_xla(options):
    """Every backend parses a program's options and refuses an unknown one: what rbdyn_jax
    passes (and advises a caller to pass) compiles on the running jaxlib."""
    f = jax.jit(lambda x: jnp.cos(x), compiler_options=options)
    assert float(f(0.5)) == pytest.approx(np.cos(0.5))


@pytest.mark.parametrize("name", sorted(_xla.RETIRED))
def test_retired_options_are_refused_exactly_from_their_jaxlib(name):
    """`RETIRED` is what the running XLA does: an option it lists is refused from its
    jaxlib on and compiles before it; `known_options` keeps it only before."""
    value = rb.COMPILER_OPTIONS.get(name, False)
    f = jax.jit(lambda x: x + 1, compiler_options={name: value})
    if _xla.jaxlib_version() >= _xla.RETIRED[name]:
        with pytest.raises(Exception, match="No such compile option"):
            f(1.0)
        assert name not in rb.COMPILER_OPTIONS
    else:
        assert float(f(1.0)) == 2.0
        assert name in rb.COMPILER_OPTIONS
    first = _xla.RETIRED[name]
    assert name in _xla.known_options({name: value}, (first[0], first[1] - 1))
    assert _xla.known_options({name: value, "other": 1}, first) == {"other": 1}


def direct_jits(path: pathlib.Path) -> list[int]:
    """Lines of the file at `path` that name `jax.jit` or `eqx.filter_jit` in code (not in
    strings): a program compiled without `_xla.COMPILER_OPTIONS`."""
    return sorted(
        node.lineno
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute)
        and (node.attr, getattr(node.value, "id", None)) in {("jit", "jax"), ("filter_jit", "eqx")}
    )


def test_every_program_is_compiled_through_xla():
    """`_program/xla.py` owns how rbdyn_jax compiles: every other module jits through its `jit` and
    `filter_jit`, which pass `COMPILER_OPTIONS` (a jit of its own would compile without
    them, ~1/3 slower on CPU)."""
    found = {
        str(p.relative_to(PACKAGE)): direct_jits(p)
        for p in PACKAGE.rglob("*.py")
        if p.relative_to(PACKAGE).as_posix() != "_program/xla.py"
    }
    assert not {k: v for k, v in found.items() if v}


def test_jit_checker_sees_a_direct_jit(tmp_path):
    bad = tmp_path / "m.py"
    bad.write_text(
        '"""jax.jit in a docstring"""\nimport jax\nf = jax.jit(g)\n\n'
        "@eqx.filter_jit\ndef h(): ...\n"
    )
    assert direct_jits(bad) == [3, 5]


# `configure_xla`: XLA's process-wide flags. The merge is checked on the string; what the
# flags do is checked in a fresh process, since XLA reads them once, when JAX starts it.

LOOP = f"{_xla_flags.LOOP_OPTION}={_xla_flags.LOOP_BYTES}"
COUNT = "--xla_force_host_platform_device_count"


@pytest.fixture
def flags(monkeypatch):
    """`configure_xla` on a given XLA_FLAGS, as if JAX had not started XLA yet and the
    import had set no device count."""
    monkeypatch.setattr(_xla_flags, "backend_started", lambda: False)
    monkeypatch.setattr(_xla_flags, "_count_set_on_import", None)

    def run(old, **kwargs):
        if old is None:
            monkeypatch.delenv("XLA_FLAGS", raising=False)
        else:
            monkeypatch.setenv("XLA_FLAGS", old)
        new = _xla.configure_xla(**kwargs)
        assert os.environ["XLA_FLAGS"] == new
        return new

    return run


def test_configure_xla_adds_its_flags(flags):
    assert flags(None) == f"--xla_backend_extra_options={LOOP}"
    assert flags("", host_devices=3) == (
        f"--xla_backend_extra_options={LOOP} --xla_force_host_platform_device_count=3"
    )
    again = flags(flags("--xla_dump_to=/tmp/x", host_devices=2), host_devices=2)
    assert again == (
        f"--xla_dump_to=/tmp/x --xla_backend_extra_options={LOOP} "
        "--xla_force_host_platform_device_count=2"
    )  # idempotent


def test_configure_xla_keeps_what_xla_flags_already_say(flags):
    # Other backend options stay beside the loop threshold (XLA keeps only the last
    # `--xla_backend_extra_options`, so they must share it).
    assert flags("--xla_backend_extra_options=a=1,b=2") == (
        f"--xla_backend_extra_options=a=1,b=2,{LOOP}"
    )
    mine = f"--xla_backend_extra_options={_xla_flags.LOOP_OPTION}=0"
    assert flags(mine) == mine  # the caller's threshold wins
    count = "--xla_force_host_platform_device_count=1"
    assert flags(count, host_devices=4) == f"{count} --xla_backend_extra_options={LOOP}"


def test_configure_xla_replaces_only_the_count_the_import_set(flags, monkeypatch):
    """The device count `import rbdyn_jax` added gives way to an explicit one, which then
    stays; a count the user set, or one already in the environment the process started
    with, is kept."""
    ours = f"{COUNT}=4"
    monkeypatch.setattr(_xla_flags, "_count_set_on_import", ours)
    imported = f"--xla_backend_extra_options={LOOP} {ours}"
    assert flags(imported) == imported  # the same flags again: nothing to change
    assert flags(imported, host_devices=4) == imported
    monkeypatch.setattr(_xla_flags, "_count_set_on_import", ours)
    assert flags(imported, host_devices=1) == f"--xla_backend_extra_options={LOOP} {COUNT}=1"
    assert _xla_flags._count_set_on_import is None  # the caller's count now
    assert flags(f"--xla_backend_extra_options={LOOP} {COUNT}=1", host_devices=3) == (
        f"--xla_backend_extra_options={LOOP} {COUNT}=1"
    )
    monkeypatch.setattr(_xla_flags, "_count_set_on_import", ours)
    users = f"{COUNT}=2 --xla_backend_extra_options={LOOP}"
    assert flags(users, host_devices=1) == users


def test_configure_xla_refuses_what_would_have_no_effect(monkeypatch):
    monkeypatch.setattr(_xla_flags, "backend_started", lambda: True)
    monkeypatch.setattr(_xla_flags, "_count_set_on_import", None)
    monkeypatch.setenv("XLA_FLAGS", "")
    with pytest.raises(RuntimeError, match="already running"):
        _xla.configure_xla()
    done = f"--xla_backend_extra_options={LOOP} --xla_force_host_platform_device_count=2"
    monkeypatch.setenv("XLA_FLAGS", done)
    assert _xla.configure_xla(host_devices=2) == done  # nothing to change: no error
    for bad in (0, -1, 1.5, True, "2", np.int64(0)):
        with pytest.raises(ValueError, match="host_devices"):
            _xla.configure_xla(host_devices=bad)
    assert _xla.configure_xla(host_devices=np.int64(2)) == done  # a NumPy int is an int


def test_backend_started_is_true_in_a_running_process():
    jnp.ones(2).block_until_ready()
    assert _xla_flags.backend_started()


def test_usable_cores_is_a_positive_count_at_most_the_machines():
    assert 1 <= _xla_flags.usable_cores() <= (os.cpu_count() or 1)


# `import rbdyn_jax` in fresh processes, from an environment without XLA_FLAGS (this
# process's may hold what its own import set) unless a test gives one.
_REPORT = """
import json, os, sys
{before}
import rbdyn_jax as rb
flags = os.environ.get("XLA_FLAGS")
{after}
import jax
print(json.dumps({{"flags": flags, "now": os.environ.get("XLA_FLAGS"),
                   "devices": jax.local_device_count()}}))
"""


def fresh(before="", after="", **env):
    """What a fresh process that imports rbdyn_jax sees: XLA_FLAGS after the import and
    after `after`, and its number of XLA devices."""
    base = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", _xla_flags.OPT_OUT)}
    run = subprocess.run(
        [sys.executable, "-c", _REPORT.format(before=before, after=after)],
        env=dict(base, **env),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_import_gives_one_device_per_core_and_loops_compiled_whole():
    cores = _xla_flags.usable_cores()
    got = fresh()
    assert got["flags"] == f"--xla_backend_extra_options={LOOP} {COUNT}={cores}"
    assert got["devices"] == cores
    # JAX imported and configured first, as the examples do: it has not started XLA yet
    after_jax = fresh(before="import jax; jax.config.update('jax_enable_x64', True)")
    assert after_jax == got


@pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or _xla_flags.usable_cores() < 2,
    reason="needs CPU affinity and two cores",
)
def test_a_process_limited_to_one_core_gets_one_device():
    got = fresh(before="os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})")
    assert got["flags"] == f"--xla_backend_extra_options={LOOP} {COUNT}=1"
    assert got["devices"] == 1


@pytest.mark.parametrize(
    "users, devices",
    [
        (f"{COUNT}=1", 1),
        (f"{COUNT}=1 --xla_cpu_multi_thread_eigen=true", 1),
        (f"--xla_backend_extra_options={_xla_flags.LOOP_OPTION}=0", None),
        ("--xla_cpu_multi_thread_eigen=true", None),
    ],
    ids=["count", "count-and-other", "threshold", "other"],
)
def test_import_never_overrides_the_users_flags(users, devices):
    """Each of the user's flags stays as written; only what it leaves out is added."""
    cores = _xla_flags.usable_cores()
    got = fresh(XLA_FLAGS=users)
    assert got["flags"].startswith(users)
    assert got["flags"].split()[: len(users.split())] == users.split()
    assert got["flags"].count(COUNT) == 1 and got["flags"].count(_xla_flags.LOOP_OPTION) == 1
    assert got["devices"] == (devices or cores)
    if _xla_flags.LOOP_OPTION in users:
        assert f"{_xla_flags.LOOP_OPTION}=0" in got["flags"]


def test_opting_out_leaves_xla_flags_alone():
    assert fresh(RBDYN_JAX_CONFIGURE_XLA="0") == {"flags": None, "now": None, "devices": 1}
    users = "--xla_cpu_multi_thread_eigen=true"
    got = fresh(RBDYN_JAX_CONFIGURE_XLA="0", XLA_FLAGS=users)
    assert got == {"flags": users, "now": users, "devices": 1}


def test_import_after_jax_computed_changes_nothing():
    """XLA has read its flags: the import changes none and raises nothing, and the library
    runs on the device JAX started."""
    got = fresh(
        before="import jax; jax.numpy.ones(2).block_until_ready()",
        after="jnp = jax.numpy; rb.simulate(rb.RigidBody(jnp.eye(3)), rb.State("
        "jnp.ones(3), jnp.array([1.0, 0, 0, 0])), jnp.array([0.0, 1.0]))",
    )
    assert got == {"flags": None, "now": None, "devices": 1}


def test_explicit_configure_xla_after_import_takes_effect():
    cores = _xla_flags.usable_cores()
    got = fresh(after="rb.configure_xla(host_devices=1)")
    assert got["flags"] == f"--xla_backend_extra_options={LOOP} {COUNT}={cores}"
    assert got["now"] == f"--xla_backend_extra_options={LOOP} {COUNT}=1"
    assert got["devices"] == 1
    again = fresh(after="rb.configure_xla()")  # what the import set: nothing changes
    assert again["now"] == again["flags"] and again["devices"] == cores


# Run in two fresh processes with the import's configuration turned off
# (`RBDYN_JAX_CONFIGURE_XLA=0`): one calling `configure_xla()` first, one with XLA's
# defaults.
# Prints the number of while loops in the compiled gradient program and of
# those compiled whole (XLA's `xla_cpu_small_call` attribute), then the outputs' file.
_PROGRAM = """
import re, sys
import rbdyn_jax as rb
if sys.argv[1] == "configure":
    rb.configure_xla()
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
J = jnp.array([[2.0, 0.05, 0.0], [0.05, 3.0, 0.02], [0.0, 0.02, 4.0]])
w0 = np.random.default_rng(0).normal(size=(24, 3))
y0s = rb.State(jnp.asarray(w0), jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (24, 1)))
ts = jnp.linspace(0.0, 10.0, 11)

def loss(theta):
    model = rb.RigidBody(rb.inertia.from_log_cholesky(theta))
    traj = rb.simulate_batch(model, y0s, ts, batching=rb.Lanes(4))
    return jnp.sum(traj.ys.omega ** 2) + jnp.sum(traj.ys.quat[..., 1:] ** 2)

theta = rb.inertia.to_log_cholesky(J)
grad = jax.jit(jax.grad(loss), compiler_options=rb.COMPILER_OPTIONS)
text = grad.lower(theta).compile().as_text()
lanes = rb.simulate_batch(rb.RigidBody(J), y0s, ts, batching=rb.Lanes(4))
plain = rb.simulate_batch(rb.RigidBody(J), y0s, ts, batching=rb.Vmap())
np.savez(sys.argv[2], lanes_omega=lanes.ys.omega, lanes_quat=lanes.ys.quat,
         plain_omega=plain.ys.omega, plain_quat=plain.ys.quat, grad=grad(theta),
         steps=lanes.stats["num_steps"])
print(len(re.findall(r"\\bwhile\\(", text)), text.count("xla_cpu_small_call"))
"""


def test_configured_xla_compiles_every_loop_whole_with_the_same_results(tmp_path):
    script = tmp_path / "program.py"
    script.write_text(_PROGRAM)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env[_xla_flags.OPT_OUT] = "0"
    run = subprocess.run(
        [sys.executable, str(script), "configure", str(tmp_path / "on.npz")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    loops, whole = map(int, run.stdout.split()[-2:])
    assert loops >= 2 and whole == loops  # the lane loop and its stage loop, and more
    here = subprocess.run(
        [sys.executable, str(script), "default", str(tmp_path / "off.npz")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert here.returncode == 0, here.stderr[-3000:]
    loops_default, whole_default = map(int, here.stdout.split()[-2:])
    assert loops_default == loops and whole_default < loops  # XLA's own threshold is small
    on, off = np.load(tmp_path / "on.npz"), np.load(tmp_path / "off.npz")
    # The same arithmetic, compiled into one function instead of kernel by kernel: equal
    # to round-off, with the same steps. The trajectories were bitwise equal. XLA fuses the
    # two programs differently and may contract a multiply-add in one and not the other;
    # the gradient, a sum over 264 outputs of the sensitivities' products, differed by
    # 2.4e-13 relative (about a thousand ulps).
    np.testing.assert_array_equal(on["steps"], off["steps"])
    for key in ("lanes_omega", "lanes_quat", "plain_omega", "plain_quat"):
        np.testing.assert_allclose(on[key], off[key], rtol=1e-13, atol=1e-13, err_msg=key)
    np.testing.assert_allclose(on["grad"], off["grad"], rtol=1e-11, atol=0, err_msg="grad")
