"""Smoke test of the `rbdyn` command: the main job runs and reports what it must."""

import re

import numpy as np

from rbdyn_jax import cli


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


def test_scenarios_lists_the_shipped_ones(capsys):
    assert cli.main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name in ("torque_free_flip", "lagrange_top_restoring", "gg_axisymmetric",
                 "rotating_platform", "satellite_gravity_gradient"):
        assert name in out


def test_sweep_and_plot_commands(tmp_path):
    """The main job end to end in a fresh process (as `make run` does, tiny): the summary
    table, the store, the plots; a bad scenario exits with the offending key."""
    import subprocess
    import sys

    import xarray as xr

    out = tmp_path / "flip.zarr"
    run = subprocess.run(
        [sys.executable, "-m", "rbdyn_jax.cli", "sweep", "torque_free_flip", "--n", "40",
         "--chunk", "16", "--lanes", "8", "--out", str(out)],
        capture_output=True, text=True, timeout=300, check=True)
    assert "successful" in run.stdout and "first_flip_time" in run.stdout
    assert "traj/s" in run.stderr  # the progress bar
    ds = xr.open_zarr(out)
    assert ds.sizes["trajectory"] == 40 and bool(ds.attrs["complete"])
    # spun 0.02 rad/s-dispersed about the intermediate axis: every body flips within 40 s
    flips = ds.first_flip_time.values
    assert np.all((flips > 0) & (flips < 40))
    plots = subprocess.run([sys.executable, "-m", "rbdyn_jax.cli", "plot", str(out)],
                           capture_output=True, text=True, timeout=300, check=True)
    written = [line.split(" ", 1)[1] for line in plots.stdout.splitlines()
               if line.startswith("wrote ")]
    assert len(written) == 4 and all(p.endswith(".png") for p in written)
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\nkind = "rigid_body"\n[model.inertia]\nprincipal = [1, 1, 3]\n'
                   '[initial]\nomega = [0, 1, 0]\n[time]\nt1 = 1\nn = 3\n')
    fail = subprocess.run([sys.executable, "-m", "rbdyn_jax.cli", "sweep", str(bad), "--n", "2",
                           "--out", str(tmp_path / "bad.zarr")], capture_output=True, text=True,
                          timeout=300)
    assert fail.returncode == 2 and "`model.inertia.principal`" in fail.stderr
