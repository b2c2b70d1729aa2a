"""The `rbdyn` command ends cleanly: exit statuses and messages for damaged, incomplete and
missing stores, unwritable paths, and Ctrl-C (a real SIGINT to a real process)."""

import os
import shlex
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr

from rbdyn_jax import cli
from rbdyn_jax.cli import _sweep as cli_sweep


@pytest.fixture
def no_cache(monkeypatch):
    """Keep JAX's persistent compilation cache off for the other tests (`rbdyn sweep` in
    this process turns it on unless `$RBDYN_JAX_CACHE_DIR` is empty)."""
    monkeypatch.setenv("RBDYN_JAX_CACHE_DIR", "")


def _toml(path, t1=4.0):
    path.write_text(
        'name = "tiny"\n[model]\nkind = "rigid_body"\n[model.inertia]\n'
        "principal = [1.0, 2.0, 2.5]\nlog_cholesky_sigma = 0.05\n"
        '[initial]\nomega = { dist = "normal", mean = [0.1, 1.0, 0.1], std = 0.3 }\n'
        f"[time]\nt1 = {t1}\nn = 5\n[solver]\nrtol = 1e-8\natol = 1e-8\n"
        '[outputs]\nsummaries = ["energy_drift"]\n'
    )
    return path


@pytest.fixture
def store(tmp_path, no_cache, capsys):
    out = tmp_path / "s.zarr"
    assert (
        cli.main(
            [
                "sweep",
                str(_toml(tmp_path / "tiny.toml")),
                "--n",
                "16",
                "--chunk",
                "8",
                "--lanes",
                "8",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    return out


def _chunk_file(store, name, i):
    a = zarr.open_group(str(store), mode="r")[name]
    return store / name / a.metadata.encode_chunk_key((i,) + (0,) * (a.ndim - 1))


def test_verify_export_and_plot_on_damaged_and_incomplete_stores(store, tmp_path, capsys):
    assert cli.main(["verify", str(store)]) == 0
    assert "whole and complete" in capsys.readouterr().out
    os.remove(_chunk_file(store, "omega", 1))
    assert cli.main(["verify", str(store)]) == cli.EXIT_DAMAGED == 5
    out = capsys.readouterr().out
    assert "omega chunk 1: missing (trajectories 8..15)" in out
    assert (
        f"finish it with: rbdyn sweep SCENARIO.toml --n 16 --trajectories all --dtype "
        f"float64 --out {store} --resume"
    ) in out
    for args in (["export", str(store), str(tmp_path / "s.nc")], ["plot", str(store)]):
        assert cli.main(args) == cli.EXIT_DAMAGED
        err = capsys.readouterr().err
        assert f"rbdyn verify {store}" in err and "--resume" in err and "Traceback" not in err
    assert not (tmp_path / "s.nc").exists()
    # Resumed, the store is whole again; then with a trajectory not run it is incomplete.
    assert (
        cli.main(
            [
                "sweep",
                str(tmp_path / "tiny.toml"),
                "--n",
                "16",
                "--lanes",
                "8",
                "--out",
                str(store),
                "--resume",
            ]
        )
        == 0
    )
    capsys.readouterr()
    zarr.open_group(str(store), mode="r+")["status"][3] = -1
    assert cli.main(["verify", str(store)]) == cli.EXIT_INCOMPLETE == 7
    assert "incomplete: 1 of 16" in capsys.readouterr().out
    assert cli.main(["export", str(store), str(tmp_path / "s.nc")]) == 0
    err = capsys.readouterr().err
    assert "rbdyn export: warning:" in err and "1 of 16 trajectories not solved" in err
    assert cli.main(["verify", str(tmp_path / "nowhere.zarr")]) == cli.EXIT_USAGE == 2
    assert "not a sweep store" in capsys.readouterr().err


def test_user_errors_exit_2_with_one_message(tmp_path, no_cache, capsys):
    toml = str(_toml(tmp_path / "tiny.toml"))
    cases = {
        "/proc/forbidden.zarr": "cannot write /proc/forbidden.zarr",  # not writable
        str(tmp_path / "missing.zarr"): "no sweep store",  # --resume, nothing there
    }
    for out, message in cases.items():
        extra = ["--resume"] if "missing" in out else []
        assert cli.main(["sweep", toml, "--n", "4", "--lanes", "8", "--out", out, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
        assert len([line for line in err.splitlines() if line.startswith("rbdyn")]) == 1
    assert not (tmp_path / "missing.zarr").exists()
    assert cli.main(["export", str(tmp_path), str(tmp_path / "x.nc")]) == 2
    assert "not a sweep store" in capsys.readouterr().err


def test_ctrl_c_exits_130_and_names_the_resume_command(tmp_path, no_cache):
    """SIGINT to a real `rbdyn sweep` mid-run: status 130, the solved count, the command
    that finishes the sweep, no traceback; that command (run here as `rbdyn` runs it, by
    `cli.main`) then finishes it."""
    toml = _toml(tmp_path / "slow.toml", t1=150.0)
    out = tmp_path / "i.zarr"
    # 64 chunks: the run outlasts the poll below on a loaded machine (about 0.1 s a chunk).
    argv = ["sweep", str(toml), "--n", "512", "--chunk", "8", "--lanes", "16", "--out", str(out)]
    env = dict(os.environ, RBDYN_JAX_CACHE_DIR="")
    # SIGINT handled as in a terminal's shell: a pytest-xdist worker ignores it, and a child
    # started with it ignored keeps ignoring it (Python then installs no handler).
    # (The child installs Python's handler itself: no fork-time hook in this JAX process.)
    code = (
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"
        "; sys.argv = ['rbdyn', *sys.argv[1:]]"
        "; runpy.run_module('rbdyn_jax.cli', run_name='__main__')"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            time.sleep(0.02)
            try:
                if np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0) >= 8:
                    break
            except Exception:  # store not created yet
                continue
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == cli.EXIT_INTERRUPTED == 130, stderr[-2000:]
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    line = next(x for x in stderr.splitlines() if "interrupted:" in x)
    done = int(np.sum(zarr.open_group(str(out), mode="r")["status"][:] >= 0))
    assert 0 < done < 512, "the signal did not land mid-run"
    assert f"interrupted: {done} of 512 solved; finish with `" in line
    command = shlex.split(line.split("`")[1])
    assert command[0] == "rbdyn" and command[-1] == "--resume"
    assert cli.main(command[1:]) == 0  # as the `rbdyn` command runs it
    assert np.all(zarr.open_group(str(out), mode="r")["status"][:] == 0)


def test_progress_in_a_log_is_lines(tmp_path, no_cache, capsys, monkeypatch):
    """Not a terminal: a line every few seconds and at the end, never a redrawn bar."""
    monkeypatch.setattr(cli_sweep, "LOG_EVERY", 0.0)  # every chunk
    assert (
        cli.main(
            [
                "sweep",
                str(_toml(tmp_path / "tiny.toml")),
                "--n",
                "16",
                "--chunk",
                "8",
                "--lanes",
                "8",
                "--out",
                str(tmp_path / "s.zarr"),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "\r" not in err
    assert "solved 8 of 16 (50 %), 0 failed" in err and "solved 16 of 16 (100 %)" in err
    shutil.rmtree(tmp_path / "s.zarr")
