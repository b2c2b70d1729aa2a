"""Smoke test of the `rbdyn` command: the main job runs and reports what it must."""

import ast
import os
import pathlib
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

import rbdyn_jax
from rbdyn_jax import cli
from rbdyn_jax.cli import _fit as cli_fit
from rbdyn_jax.scenario import Scenario, list_scenarios


def test_demo_simulates_the_default_body(capsys):
    assert cli.main(["demo", "--steps", "2", "--duration", "30"]) == 0
    out = capsys.readouterr().out
    assert "physically consistent: True" in out
    assert "result: successful" in out
    # Principal moments printed ascending and satisfying the triangle inequality.
    A, B, C = map(float, re.search(r"A ≤ B ≤ C: ([0-9.]+), ([0-9.]+), ([0-9.]+)", out).groups())
    assert A <= B <= C and A + B >= C
    np.testing.assert_allclose(B, 0.40815, atol=1e-5)  # the shipped default body
    # Started 1° off the intermediate axis, the body flips within 30 s (period ≈ 19 s).
    assert int(re.search(r"flips: (\d+)", out).group(1)) >= 1
    # The first integrals hold to the solver tolerance (rtol = atol = 1e-10; ×10 margin).
    energy = float(re.search(r"energy drift .*?:\s+([0-9.e+-]+)", out).group(1))
    momentum = float(re.search(r"momentum drift .*?:\s+([0-9.e+-]+)", out).group(1))
    assert energy < 1e-9 and momentum < 1e-9


def test_version_is_the_package_version(capsys):
    """`rbdyn --version` prints `rbdyn <version>` with the version the package reports."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"rbdyn {rbdyn_jax.__version__}"


def test_version_of_the_installed_command():
    """The installed `rbdyn` script, in a fresh process, reports the same version."""
    script = shutil.which("rbdyn", path=str(pathlib.Path(sys.executable).parent))
    if script is None:
        pytest.skip("the `rbdyn` script is not installed beside this Python")
    run = subprocess.run(
        [script, "--version"], capture_output=True, text=True, timeout=300, check=True
    )
    assert run.stdout.strip() == f"rbdyn {rbdyn_jax.__version__}"


def test_cli_imports_jax_only_inside_commands():
    """The `cli` package's modules import nothing heavy at module level: JAX and the
    numerical stack are imported inside the commands that compute, so `--help` and
    `--version` need none of them (its version comes from `_version.py`, which imports
    nothing). At their top they import the standard library's lightest modules, each other
    and `_version`."""
    package = pathlib.Path(cli.__file__).parent
    files = sorted(package.glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "__main__.py", "_main.py", "_parser.py"}
    for path in files:
        top = set()
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Import):
                top.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                top.add(
                    "." * node.level + (node.module or "")
                    if node.level
                    else (node.module or "").split(".")[0]
                )
        siblings = {"." + f.stem for f in files} | {"."}
        assert top <= {
            "argparse",
            "os",
            "shlex",
            "sys",
            "time",
            "warnings",
            ".._version",
            *siblings,
        }, (path.name, top)
    version = package.with_name("_version.py").read_text()
    assert "import" not in version


def test_scenarios_lists_the_shipped_ones(capsys):
    assert cli.main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name in (
        "torque_free_flip",
        "lagrange_top_restoring",
        "gg_axisymmetric",
        "rotating_platform",
        "satellite_gravity_gradient",
    ):
        assert name in out


# What `--help`, `--version` and `scenarios` print, as the commands' own code builds it:
# the parser's help, the version, and each shipped scenario validated by `Scenario.load`.
_QUICK = {
    "--help": lambda: cli.build_parser().format_help(),
    "--version": lambda: f"rbdyn {rbdyn_jax.__version__}\n",
    "scenarios": lambda: "".join(
        f"{name:28s} {Scenario.load(name).description}\n" for name in list_scenarios()
    ),
}


@pytest.mark.parametrize("command", list(_QUICK))
def test_quick_commands_print_the_same_without_importing_jax(command, monkeypatch):
    """`rbdyn --help`, `--version` and `scenarios` in a fresh process import neither JAX
    nor NumPy, and print what the parser, the package and the validated scenarios say."""
    code = (
        "import sys\nfrom rbdyn_jax import cli\n"
        "try:\n    code = cli.main(sys.argv[1:])\n"
        "except SystemExit as e:\n    code = e.code\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('jax', 'jaxlib', 'numpy'))\n"
        "assert not heavy, heavy\nsys.exit(code)\n"
    )
    monkeypatch.setenv("COLUMNS", "100")  # argparse's width, here and in the child
    run = subprocess.run(
        [sys.executable, "-c", code, command],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, COLUMNS="100"),
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout == _QUICK[command]()


def test_sweep_and_plot_commands(tmp_path):
    """The main job end to end in a fresh process (as `make run` does, tiny): the summary
    table, the store, the plots; a bad scenario exits with the offending key."""
    import os
    import subprocess
    import sys

    import xarray as xr

    out = tmp_path / "flip.zarr"
    env = dict(os.environ, RBDYN_JAX_CACHE_DIR=str(tmp_path / "cache"))
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "rbdyn_jax.cli",
            "sweep",
            "torque_free_flip",
            "--n",
            "40",
            "--chunk",
            "16",
            "--lanes",
            "8",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
        env=env,
    )
    # the sweep's program has no host callbacks, so JAX's persistent cache stores it
    assert any((tmp_path / "cache").iterdir())
    assert "successful" in run.stdout and "first_flip_time" in run.stdout
    # not a terminal: progress as lines, not a redrawn bar
    assert "solved 40 of 40 (100 %), 0 failed" in run.stderr and "\r" not in run.stderr
    ds = xr.open_zarr(out)
    assert ds.sizes["trajectory"] == 40 and bool(ds.attrs["complete"])
    # spun 0.02 rad/s-dispersed about the intermediate axis: every body flips within 40 s
    flips = ds.first_flip_time.values
    assert np.all((flips > 0) & (flips < 40))
    plots = subprocess.run(
        [sys.executable, "-m", "rbdyn_jax.cli", "plot", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    written = [
        line.split(" ", 1)[1] for line in plots.stdout.splitlines() if line.startswith("wrote ")
    ]
    assert len(written) == 4 and all(p.endswith(".png") for p in written)
    bad = tmp_path / "bad.toml"
    bad.write_text(
        '[model]\nkind = "rigid_body"\n[model.inertia]\nprincipal = [1, 1, 3]\n'
        "[initial]\nomega = [0, 1, 0]\n[time]\nt1 = 1\nn = 3\n"
    )
    fail = subprocess.run(
        [
            sys.executable,
            "-m",
            "rbdyn_jax.cli",
            "sweep",
            str(bad),
            "--n",
            "2",
            "--out",
            str(tmp_path / "bad.zarr"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert fail.returncode == 2 and "`model.inertia.principal`" in fail.stderr


def test_fit_command_recovers_the_inertia_from_csv(tmp_path, capsys, no_cache):
    """`rbdyn fit` on a CSV of noisy ω and attitude of a heavy top (a known torque fixes the
    scale of J): the fitted inertia is within 4 standard errors, the files are written."""
    import json

    import jax.numpy as jnp

    import rbdyn_jax as rb

    J_true = np.array([[2.0, 0.1, -0.05], [0.1, 3.0, 0.08], [-0.05, 0.08, 3.5]])
    gravity = rb.UniformGravity(2.0, jnp.array([0.0, 0.0, 0.1]))
    ts = np.linspace(0.0, 3.0, 16)
    w0 = np.array([[0.5, -1.0, 0.8], [1.0, 0.4, -0.6]])
    q0 = np.array([[0.9, 0.3, 0.1, 0.2], [0.7, -0.2, 0.6, 0.1]])
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    traj = rb.simulate_batch(
        rb.RigidBody(jnp.asarray(J_true), gravity),
        rb.State(jnp.asarray(w0), jnp.asarray(q0)),
        ts,
        rtol=1e-12,
        atol=1e-12,
        throw=True,
    )
    rng = np.random.default_rng(1)
    sw, sq = 1e-3, 1e-3
    w = np.asarray(traj.ys.omega) + sw * rng.standard_normal((2, 16, 3))
    dq = rb.rotation.quat_from_rotvec(jnp.asarray(sq * rng.standard_normal((2, 16, 3))))
    q = np.asarray(rb.rotation.quat_multiply(traj.ys.quat, dq))
    rows = ["trajectory,t,wx,wy,wz,qw,qx,qy,qz"]
    for k in range(2):
        for i in range(16 - k):  # the second record is one sample shorter (padding)
            rows.append(",".join(repr(float(x)) for x in [k, ts[i], *w[k, i], *q[k, i]]))
    (tmp_path / "obs.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "top.toml").write_text(
        '[model]\nkind = "rigid_body"\n[model.inertia]\nprincipal = [2.2, 2.8, 3.3]\n'
        '[[model.torques]]\nkind = "uniform_gravity"\nweight = 2.0\ncom = [0.0, 0.0, 0.1]\n'
        "[initial]\nomega = [0, 0, 0]\n[time]\nt1 = 3.0\nn = 16\n"
        '[outputs]\nsummaries = ["energy_drift"]\n'
    )
    out = tmp_path / "fit"
    argv = [
        "fit",
        str(tmp_path / "obs.csv"),
        "--model",
        str(tmp_path / "top.toml"),
        "--free",
        "inertia,ic",
        "--sigma-omega",
        str(sw),
        "--sigma-quat",
        str(sq),
        "--steps",
        "12",
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "inertia J ± stderr" in text and "2 trajectories × 16 samples" in text
    report = json.loads((out / "fit.json").read_text())
    J, se = np.array(report["inertia"]), np.array(report["inertia_stderr"])
    assert np.all(np.isfinite(se)) and np.all(se < 0.05)
    assert np.max(np.abs(J - J_true) / se) < 4.0  # Gaussian errors: 4σ over 6 entries
    assert (out / "fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a second fit into the same folder replaces its files only when asked: refused at once
    before = (out / "fit.json").read_bytes()
    again = ["fit", str(tmp_path / "obs.csv"), "--model", str(tmp_path / "top.toml")]
    assert cli.main([*again, "--steps", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "fit.json and " in err and "already there: pass --overwrite" in err
    assert (out / "fit.json").read_bytes() == before
    # the same fit again (its program already compiled in this process), asked to replace
    assert cli.main([*argv, "--overwrite"]) == 0
    assert (out / "fit.json").read_bytes() != before  # its own time
    capsys.readouterr()
    # a bad file exits 2 with the reason
    (tmp_path / "bad.csv").write_text("time,wx\n0,1\n")
    assert (
        cli.main(
            [
                "fit",
                str(tmp_path / "bad.csv"),
                "--model",
                str(tmp_path / "top.toml"),
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "`t` column" in capsys.readouterr().err


def test_free_k_picks_only_the_restoring_coefficients():
    import jax.numpy as jnp

    import rbdyn_jax as rb

    torque = rb.RestoringMoment(rb.PolynomialSinPsi(jnp.array([1.0, 0.5]), 0.1)) + rb.BodyTorque(
        jnp.array([0.0, 0.0, 1e-3])
    )
    params, where = cli_fit.free_params(["inertia", "k"], torque)
    assert params == ("inertia", "torque")
    (coeffs,) = where(torque)
    assert coeffs is torque.torques[0].k.coeffs
    import pytest

    with pytest.raises(ValueError, match="no restoring_moment"):
        cli_fit.free_params(["k"], rb.BodyTorque(jnp.zeros(3)))
    with pytest.raises(ValueError, match="unknown 'mass'"):
        cli_fit.free_params(["mass"], torque)


@pytest.fixture
def no_cache(monkeypatch):
    """`rbdyn sweep` or `rbdyn fit` run in this process turns on JAX's persistent compilation
    cache for the process, unless `$RBDYN_JAX_CACHE_DIR` is empty: keep it off for the other
    tests."""
    monkeypatch.setenv("RBDYN_JAX_CACHE_DIR", "")


def _small_toml(
    path, max_steps=None, omega='{ dist = "normal", mean = [0.1, 1.0, 0.1], std = 0.3 }', tol="1e-8"
):
    path.write_text(
        'name = "tiny"\n[model]\nkind = "rigid_body"\n[model.inertia]\n'
        "principal = [1.0, 2.0, 2.5]\n"
        f"[initial]\nomega = {omega}\n[time]\nt1 = 4.0\nn = 5\n"
        f"[solver]\nrtol = {tol}\natol = {tol}\n"
        + (f"max_steps = {max_steps}\n" if max_steps else "")
        + '[outputs]\nsummaries = ["energy_drift"]\n'
    )
    return path


def _files(path):
    return {p: p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_sweep_refuses_an_existing_store_and_exports_netcdf(tmp_path, capsys, no_cache):
    """A second sweep into a store exits 2 naming the store and both flags and changes no
    byte of it; --overwrite replaces it; `rbdyn export` writes a netCDF file xarray reads
    back equal, and refuses to overwrite it unless asked."""
    import xarray as xr

    toml = _small_toml(tmp_path / "tiny.toml")
    out = tmp_path / "s.zarr"
    args = ["sweep", str(toml), "--n", "16", "--out", str(out), "--lanes", "8"]
    assert cli.main(args) == 0
    before = _files(out)
    capsys.readouterr()
    assert cli.main([*args, "--seed", "1"]) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "--overwrite" in err and "--resume" in err
    assert _files(out) == before
    with pytest.raises(SystemExit):  # argparse: not both
        cli.main([*args, "--overwrite", "--resume"])
    assert cli.main([*args, "--seed", "1", "--overwrite"]) == 0
    attrs = xr.open_zarr(out).attrs
    assert attrs["seed"] == 1 and attrs["chunk"] == 1024  # the default on a CPU
    nc = tmp_path / "s.nc"
    assert cli.main(["export", str(out), str(nc)]) == 0
    xr.testing.assert_identical(xr.open_dataset(nc).load(), xr.open_zarr(out).load())
    capsys.readouterr()
    assert cli.main(["export", str(out), str(nc)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert cli.main(["export", str(out), str(nc), "--overwrite"]) == 0
    capsys.readouterr()
    nowhere = tmp_path / "no such folder" / "s.nc"
    assert cli.main(["export", str(out), str(nowhere)]) == 2
    assert f"cannot write {nowhere}: no folder {nowhere.parent}" in capsys.readouterr().err


def test_the_sweeps_closing_hint_quotes_its_path(tmp_path, capsys, no_cache):
    """The `rbdyn plot` line a sweep ends with runs as printed in a shell: a path with a
    space is quoted."""
    import shlex

    out = tmp_path / "a folder" / "s.zarr"
    toml = _small_toml(tmp_path / "tiny.toml")
    assert cli.main(["sweep", str(toml), "--n", "4", "--out", str(out), "--lanes", "8"]) == 0
    hint = capsys.readouterr().out.rsplit("plots: ", 1)[1].split("\n")[0]
    assert shlex.split(hint) == ["rbdyn", "plot", str(out)]


@pytest.mark.parametrize("case", ["some", "all"])
def test_sweep_exit_status_when_trajectories_fail(tmp_path, capsys, case, no_cache):
    """Exit 3 when some trajectories fail, 4 when all do, after writing everything, with
    the change to make."""
    import xarray as xr

    if case == "all":  # 3 steps cannot reach t1 = 4 at rtol 1e-8
        toml = _small_toml(tmp_path / "t.toml", max_steps=3)
    else:  # lognormal rates: some overflow (non-finite), some run out of steps
        toml = _small_toml(
            tmp_path / "t.toml",
            max_steps=400,
            omega=('{ dist = "lognormal", median = [0.3, 1.0, 0.2], sigma = [0.0, 300.0, 0.0] }'),
        )
    out = tmp_path / "f.zarr"
    code = cli.main(["sweep", str(toml), "--n", "40", "--out", str(out), "--lanes", "8"])
    status = xr.open_zarr(out).status.values
    assert np.all(status >= 0)  # everything was solved and written
    err = capsys.readouterr().err
    if case == "all":
        assert code == cli.EXIT_ALL_FAILED == 4 and np.all(status != 0)
        assert "40 of 40 trajectories failed" in err
        # the plots: the status counts only, and the note says why
        assert cli.main(["plot", str(out)]) == 0
        printed = capsys.readouterr().out
        assert "status.png" in printed and "trajectories.png" not in printed.split("note:")[0]
        assert "no trajectory whose states the store keeps succeeded" in printed
    else:
        assert code == cli.EXIT_SOME_FAILED == 3 and 0 < np.sum(status != 0) < 40
    assert "raise [solver] max_steps (now" in err


@pytest.fixture
def restore_x64():
    """`rbdyn sweep --dtype float32` turns 64-bit types off in its process: back on after."""
    yield
    import jax

    jax.config.update("jax_enable_x64", True)


def test_sweep_in_float32_of_no_states_and_its_plots(tmp_path, capsys, no_cache, restore_x64):
    """`--dtype float32 --trajectories none`: the header names the devices, the precision
    and what is stored; the run leaves 64-bit types off; the store is float32 with no
    states, `rbdyn plot` says why it draws none and `rbdyn fit` why it cannot fit it."""
    import jax
    import xarray as xr

    toml = _small_toml(tmp_path / "t.toml", tol="1e-6")
    out = tmp_path / "n.zarr"
    assert (
        cli.main(
            [
                "sweep",
                str(toml),
                "--n",
                "16",
                "--out",
                str(out),
                "--lanes",
                "8",
                "--trajectories",
                "none",
                "--dtype",
                "float32",
            ]
        )
        == 0
    )
    assert not jax.config.jax_enable_x64
    text = capsys.readouterr().out
    devices = f"on {len(jax.devices())} × cpu device"
    assert f"16 trajectories {devices}" in text and "float32, no states (summaries only)" in text
    assert "in chunks of 1024 with 8 lanes per device" in text
    ds = xr.open_zarr(out)
    assert (ds.attrs["dtype"], ds.attrs["trajectories"], ds.attrs["lanes"]) == (
        "float32",
        "none",
        8,
    )
    assert "omega" not in ds and ds.energy_drift.dtype == np.float32
    assert cli.main(["plot", str(out)]) == 0
    assert "note: no trajectories.png or polhodes.png" in capsys.readouterr().out
    assert cli.main(["fit", str(out), "--model", str(toml), "--out", str(tmp_path)]) == 2
    assert "holds no ω or attitude to fit" in capsys.readouterr().err


def test_sweep_refuses_a_dtype_or_states_the_scenario_cannot_take(tmp_path, capsys, no_cache):
    """The shipped scenarios' rtol (1e-8, 1e-9) is finer than float32 resolves: exit 2,
    naming the option and the key; `--trajectories` takes all, none or K ≥ 1."""
    out = tmp_path / "x.zarr"
    assert (
        cli.main(["sweep", "torque_free_flip", "--n", "4", "--out", str(out), "--dtype", "float32"])
        == 2
    )
    err = capsys.readouterr().err
    assert "--dtype float32" in err and "`solver.rtol`" in err and "9.5e-07" in err
    assert not out.exists()
    for bad in ("0", "-3", "some"):
        with pytest.raises(SystemExit) as e:
            cli.main(
                ["sweep", "torque_free_flip", "--n", "4", "--out", str(out), "--trajectories", bad]
            )
        assert e.value.code == 2
    assert "expected all, none or a positive integer K" in capsys.readouterr().err


def test_unreadable_scenarios_and_a_bad_duration_are_one_line_and_status_2(
    tmp_path, capsys, no_cache
):
    """A scenario path that is a folder, a file that is not UTF-8 text, and a demo
    duration that is not a positive number: one message on stderr and exit status 2, no
    traceback, nothing written."""
    folder = tmp_path / "folder.toml"
    folder.mkdir()
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    for scenario, says in ((folder, "cannot read it as a scenario"), (binary, "not valid TOML")):
        out = tmp_path / "x.zarr"
        assert cli.main(["sweep", str(scenario), "--n", "2", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert says in err and str(scenario) in err and "Traceback" not in err
        assert not out.exists()
    for bad in ("0", "-5", "nan"):
        with pytest.raises(SystemExit) as e:
            cli.main(["demo", "--duration", bad])
        assert e.value.code == 2
        assert "--duration must be a positive number" in capsys.readouterr().err
