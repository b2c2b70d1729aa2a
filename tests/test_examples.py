"""Smoke test of the example scripts: each `examples/*.py` is imported by path and its
`main()` run with tiny sizes under the strict promotion of `conftest.py`; it must write its
PNG and return finite, physically sane figures.

The bounds are loose versions of what each example shows at full size (its module docstring
and printout): solver-vs-reference errors ~100× the measured ones at these tolerances; the
O(ε) and O(ε²) errors of the averaged solutions of the restoring moment, measured ≤ 0.8 ε
and ≤ 3 ε² at ε = 0.05, bounded by 1.5 ε and 6 ε².
"""

import math

import pytest
from helpers import load_example


def _check_torque_free_flip(s):
    assert s["flips"] >= 1
    assert s["max_error_vs_elliptic"] < 1e-6
    assert s["energy_drift"] < 1e-8
    assert s["momentum_drift"] < 1e-8


def _check_rotating_platform(s):
    assert s["T_r_relative_drift"] < 1e-8
    assert s["bound_low"] - 1e-9 <= s["omega_r_min"] <= s["omega_r_max"]
    assert s["omega_r_max"] <= s["bound_high"] + 1e-9


def _check_satellite_pitch(s):
    # the period exceeds the linear one by ≈ (2θ0)²/16 = 3.0e-4 at θ0 = 2°
    assert 1e-4 < s["relative_difference"] < 6e-4


def _check_lagrange_top(s):
    eps = s["eps"]
    assert s["r_error_first"] < 1e-10
    assert 0 < s["nutation_amplitude"] < 2 * eps
    assert s["psi_error_first"] < 1.5 * eps and s["theta_error_first"] < 1.5 * eps
    assert s["psi_error_second"] < 6 * eps**2 and s["theta_error_second"] < 6 * eps**2


def _check_gg_integrable(s):
    assert s["turning_points"] >= 3
    assert s["half_period_max_relative_error"] < 1e-7
    assert s["gamma3_range_error"] < 1e-4
    for key in ("drift_r", "drift_gamma_sq", "drift_C1", "drift_C2"):
        assert s[key] < 1e-8, key


def _check_long_horizon_sweep(s):
    # order 6 at dt = 0.2 holds 1.7e-9 (measured); Tsit5 at 1e-8 drifts past 1e-7 by t = 500
    assert s["splitting_max_energy_drift"] < 1e-8
    assert s["tsit5_max_energy_drift"] > 10 * s["splitting_max_energy_drift"]
    assert s["splitting_late_over_early"] < 2.0 < s["tsit5_late_over_early"]


CASES = [
    ("torque_free_flip", dict(t_end=12.0, n_out=121), _check_torque_free_flip),
    ("rotating_platform", dict(t_end=10.0, n_out=201), _check_rotating_platform),
    ("satellite_pitch", dict(orbits=1.5, n_out=301), _check_satellite_pitch),
    ("lagrange_top", dict(eps=0.05, n_out=201), _check_lagrange_top),
    ("gg_integrable", dict(t_end=8.0, n_out=401), _check_gg_integrable),
    # needs `rbdyn_jax.sweep` to run a fixed-step scenario (`Vmap`, its `dt` as `dt0`)
    ("long_horizon_sweep", dict(n=4, t_end=500.0, n_out=401), _check_long_horizon_sweep),
]


@pytest.mark.parametrize("name, kwargs, check", CASES, ids=[c[0] for c in CASES])
def test_example_runs(name, kwargs, check, tmp_path, capsys):
    module = load_example(name)
    assert module.__doc__ and "Run:" in module.__doc__
    summary = module.main(**kwargs, out_dir=str(tmp_path))
    png = tmp_path / f"{name}.png"
    assert png.is_file() and png.stat().st_size > 1000
    assert summary and all(math.isfinite(v) for v in summary.values()), summary
    check(summary)
    assert "wrote" in capsys.readouterr().out
