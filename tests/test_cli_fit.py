"""`rbdyn fit` says when it fails: the CLI page's example converges with the default
horizons, a fit that did not converge exits with `EXIT_NOT_CONVERGED` and what to try, and
the time it prints claims compilation only where this process compiled."""

import json

import numpy as np
import pytest
import xarray as xr

from rbdyn_jax import cli
from rbdyn_jax.cli import _fit as cli_fit

# One sweep store for the module (--dist loadgroup): its sweep compiles once.
pytestmark = pytest.mark.xdist_group("cli_fit")


@pytest.fixture(autouse=True)
def no_cache(monkeypatch):
    """`rbdyn sweep` or `rbdyn fit` run in this process turns on JAX's persistent compilation
    cache for the process, unless `$RBDYN_JAX_CACHE_DIR` is empty: keep it off."""
    monkeypatch.setenv("RBDYN_JAX_CACHE_DIR", "")


@pytest.fixture(scope="module")
def flip_store(tmp_path_factory):
    """A small sweep of the shipped default scenario, as `make run` writes a large one: its
    trajectory 0 is the same draw whatever `--n` (drawn from the seed and its index)."""
    store = tmp_path_factory.mktemp("fit") / "flip.zarr"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RBDYN_JAX_CACHE_DIR", "")
        assert (
            cli.main(
                [
                    "sweep",
                    "torque_free_flip",
                    "--n",
                    "8",
                    "--lanes",
                    "1",
                    "--devices",
                    "1",
                    "--out",
                    str(store),
                ]
            )
            == 0
        )
    return store


def _fit(store, out, *extra):
    return cli.main(
        [
            "fit",
            str(store),
            "--model",
            "torque_free_flip",
            "--trajectories",
            "1",
            "--scale",
            "trace=5.5",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_the_cli_pages_example_converges_and_a_whole_record_fit_exits_6(
    flip_store, tmp_path, capsys
):
    """`rbdyn fit runs/flip.zarr --model torque_free_flip --trajectories 1 --scale
    trace=5.5` (docs/cli.md): with the default horizons it converges to the drawn inertia
    (exit 0). Fitted whole at once (`--horizons 1`) the same record stalls in a local minimum:
    exit 6, the files still written, and on stderr what to try first, the horizons."""
    ds = xr.open_zarr(flip_store)
    assert int(ds.status.values[0]) == 0  # trajectory 0 is the one fitted
    truth = ds.inertia.values[0]
    truth = truth * 5.5 / np.trace(truth)  # torque-free data fix J up to scale: tr J = 5.5
    capsys.readouterr()

    assert _fit(flip_store, tmp_path / "staged") == 0
    out = capsys.readouterr().out
    assert "horizons 0.25, 0.5, 1 of each record" in out and "converged: True" in out
    # the first fit of these sizes in this process, with the persistent cache off
    assert "of it tracing and compiling" in out and "cache" not in out
    report = json.loads((tmp_path / "staged" / "fit.json").read_text())
    assert report["converged"]
    # Noiseless data solved at rtol = atol = 1e-8: the fit agrees to 5e-8 (measured); 1e-4
    # is far below the stalled fit's error (0.95 on J_xx).
    np.testing.assert_allclose(report["inertia"], truth, rtol=0, atol=1e-4)
    assert (tmp_path / "staged" / "fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    assert _fit(flip_store, tmp_path / "whole", "--horizons", "1") == cli.EXIT_NOT_CONVERGED
    captured = capsys.readouterr()
    assert "converged: False" in captured.out
    # its program is the first stage's, compiled above: no claim of compiling
    assert "compil" not in captured.out.splitlines()[1]
    assert "rbdyn fit: the fit did not converge" in captured.err
    assert "--horizons 0.25,0.5,1" in captured.err and "start nearer the truth" in captured.err
    report = json.loads((tmp_path / "whole" / "fit.json").read_text())
    assert not report["converged"]
    assert abs(report["inertia"][0][0] - truth[0, 0]) > 0.1  # far from the truth: stalled
    assert (tmp_path / "whole" / "fit.png").exists()


def test_a_fit_with_too_few_steps_exits_6_and_asks_for_more(flip_store, tmp_path, capsys):
    """One Levenberg–Marquardt step cannot converge: exit 6, and the first thing to try is
    more steps (the loss is still falling); the staged fit's next try, finer horizons."""
    capsys.readouterr()
    assert _fit(flip_store, tmp_path, "--steps", "1") == cli.EXIT_NOT_CONVERGED
    captured = capsys.readouterr()
    assert "converged: False" in captured.out and "at most 1 step each" in captured.out
    hints = captured.err.splitlines()
    assert hints[0].startswith("rbdyn fit: the fit did not converge")
    assert "is still falling" in hints[1] and "--steps 30" in hints[1]
    assert any("--horizons 0.125,0.25,0.375,0.5,0.75,1" in h for h in hints)
    assert any("--trajectories 2" in h for h in hints)
    assert not json.loads((tmp_path / "fit.json").read_text())["converged"]


def test_the_time_claims_only_what_happened():
    """The wording of the fit's time, from what `_compile_meter` counted."""
    meter = {"tracing_s": 3.94, "loaded": 0}
    assert cli_fit.time_text(4.71, meter) == "4.7 s (3.9 s of it tracing and compiling)"
    meter = {"tracing_s": 0.1, "loaded": 2}  # small programs around the loaded fit
    assert cli_fit.time_text(0.52, meter) == "0.5 s (program loaded from the cache)"
    meter = {"tracing_s": 2.1, "loaded": 1}  # the trace redone, the compiled program loaded
    assert cli_fit.time_text(2.6, meter) == (
        "2.6 s (program loaded from the cache, 2.1 s of it tracing and compiling)"
    )
    assert cli_fit.time_text(0.31, {"tracing_s": 0.0, "loaded": 0}) == "0.3 s"
