"""Smoke tests of the identification examples (`examples/identify_*.py`): each
`main()` runs at a reduced size under the strict promotion of `conftest.py`, writes its PNG,
and recovers its parameters: within 4 standard errors of the truth, with standard errors
small against the parameters (the data determine them), converged.

Compilation dominates (one truth simulation and one fit per example).
"""

import math

import numpy as np
from helpers import load_example


def _run(name, tmp_path, capsys, **kwargs):
    module = load_example(name)
    assert module.__doc__ and "Run:" in module.__doc__
    summary = module.main(**kwargs, out_dir=str(tmp_path))
    png = tmp_path / f"{name}.png"
    assert png.is_file() and png.stat().st_size > 1000
    assert summary and all(math.isfinite(v) for v in summary.values()), summary
    assert "wrote" in capsys.readouterr().out
    return module, summary


def test_identify_inertia(tmp_path, capsys):
    module, s = _run("identify_inertia", tmp_path, capsys, n_samples=30, t_end=4.0, steps=12)
    assert s["converged"] == 1.0 and s["scale_identified"] == 1.0
    assert s["physical_iterates"] == 1.0
    assert s["max_error_in_stderr"] < 4.0
    # Every entry is recovered within 4 stderr; the stderr are far below the smallest
    # product of inertia (0.05), so the products are determined, not merely bounded.
    for name, v in zip(module.ENTRY_NAMES, module.J_TRUE[module.UPPER], strict=True):
        assert abs(s[f"J_fit_{name}"] - v) < 4 * s[f"stderr_{name}"], name
    assert s["max_stderr"] < 0.1 * s["min_abs_product"]
    assert s["max_abs_error"] < 0.01
    assert 0.7 < s["chi2_per_dof"] < 1.3


def test_identify_restoring_moment(tmp_path, capsys):
    module, s = _run("identify_restoring_moment", tmp_path, capsys, n_samples=61, steps=6)
    assert s["converged"] == 1.0
    truth = np.asarray(module.K_TRUE)
    fitted = np.array([s["K0_fit"], s["K1_fit"]])
    se = np.array([s["K0_stderr"], s["K1_stderr"]])
    assert np.all(np.abs(fitted - truth) < 4 * se), (fitted, se)
    assert np.all(se < 0.05 * np.abs(truth)), se  # a few % of K0 = 1 and K1 = 0.5
    # The K(τ) band propagated through the 2×2 covariance covers the truth.
    assert s["K_max_error_in_sigma"] < 4.0
    assert s["omega0_error"] < 1e-2
    assert 0.6 < s["chi2_per_dof"] < 1.4
