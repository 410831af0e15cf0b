"""The cheap Roman-table path gives the slopes of the path it replaced (docs/field.md, "Cost of one table").

Three checks, from the pixel up: the optimal-fit factors against a generalised least-squares solve
written here from the covariance built read by read; the coupled-powers scene factors
(``ramps.scene_factors_coupled``: IPC of the unit stamps' powers, the moments' core only) against
``ramps.scene_factors``, which couples every read of every pixel; and whole slopes of a small Roman
table with the new path against the same table with the old one put back.
"""

import numpy as np
import pytest

from nlpsf.sim import experiment, ramps
from nlpsf.sim import scene as scenes
from nlpsf.sim.ramps.fits import _factors_for  # the factors for given usable resultants
from nlpsf.slopes import tablebuild

FULL_WELL = 1.1e5
BETA = 5e-7
KERNEL = np.asarray(scenes.ROMAN_IPC_KERNEL)

#: Every public name of nlpsf/ramps.py before it became a package (``from nlpsf.sim import ramps; ramps.X``).
OLD_PUBLIC_NAMES = [
    "DEFAULT_READ_NOISE_E",
    "MATable",
    "MAX_READS",
    "RAMP_FITS",
    "RAMP_REFUSES",
    "ROMAN_FRAME_TIME_S",
    "Ramp",
    "RampImage",
    "SATURATION_RULES",
    "SINGLE_RESULTANT_RULES",
    "SceneRamp",
    "build",
    "check_scene",
    "load_ma_table",
    "nonlinearity_perturbation",
    "order_factors",
    "polynomial_perturbation",
    "polynomial_response",
    "resultant_means",
    "scene_factors",
    "scene_perturbation",
    "shipped_table_dir",
    "shipped_table_names",
    "signal_usable",
    "simulate_pixels",
    "slope_weights",
    "usable_resultants",
    "usage_summary",
]


def test_the_ramps_package_keeps_every_public_name():
    assert [name for name in OLD_PUBLIC_NAMES if not hasattr(ramps, name)] == []


def _gls_factor(q, k, table, exptime, read_noise, order=2):
    """c_n = w . <tau^n>_j with w the best linear unbiased slope on the first k resultants, by an
    explicit solve: C_ij = sigma^2 / n_i delta_ij + q (1 / n_i n_j) sum_{a in i, b in j} min(tau_a, tau_b)."""
    reads = [np.array(r[:], dtype=float) * table.frame_time_s / exptime for r in table.resultants[:k]]
    mean = np.array([t.mean() for t in reads])
    C = np.array([[q * np.mean(np.minimum.outer(a, b)) for b in reads] for a in reads])
    C += np.diag([read_noise**2 / len(t) for t in reads])
    X = np.stack([np.ones(k), mean], axis=1)
    Ci = np.linalg.inv(C)
    w = np.linalg.solve(X.T @ Ci @ X, X.T @ Ci)[1]
    return float(w @ np.array([np.mean(t**order) for t in reads]))


def test_optimal_factors_equal_an_explicit_generalised_least_squares_solve():
    ramp, exptime = ramps.build(ma_table="C2A_IMG_HLWAS", fit="optimal", sca=18)
    table = ramp.table
    charges = np.array([0.0, 3.0, 250.0, 4e3, 6e4, 3e5, 1e6])
    for k in (2, 5, table.n_resultants):
        got = _factors_for(charges, np.full(charges.size, k), ramp, exptime, (2, 3))
        for q, c2, c3 in zip(charges, got[0], got[1], strict=True):
            assert c2 == pytest.approx(_gls_factor(q, k, table, exptime, ramp.read_noise_e, 2), rel=1e-10)
            assert c3 == pytest.approx(_gls_factor(q, k, table, exptime, ramp.read_noise_e, 3), rel=1e-10)


def _stamps(n=48, realizations=3, oversampling=3, seed=4):
    """Gaussian stars (sigma 4 fine pixels) at sub-pixel offsets: unit-flux charge per fine pixel."""
    rng = np.random.default_rng(seed)
    c = np.arange(n) - (n - 1) / 2
    out = []
    for dx, dy in rng.uniform(-1.5, 1.5, (realizations, 2)):
        g = np.exp(-((c[None, :] - dx) ** 2 + (c[:, None] - dy) ** 2) / (2 * 4.0**2))
        out.append(g / g.sum())
    return np.array(out)


@pytest.mark.parametrize("saturation", ["signal", "charge"])
@pytest.mark.parametrize("coefficients", [(BETA,), (BETA, 2e-12)])
def test_coupled_scene_factors_equal_coupling_every_read(saturation, coefficients):
    ramp, exptime = ramps.build(ma_table="C2A_IMG_HLWAS", fit="optimal", sca=18, saturation=saturation)
    unit = _stamps()
    powers = ramps.CoupledPowers(unit, KERNEL, 3)
    background = 80.0
    orders = tuple(range(2, 2 + len(coefficients)))
    n, margin = unit.shape[-1], 10
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    # Faint (nothing saturates), near the ramp's limit and far past it (most resultants of the core lost).
    for scale in (2e3, 3e6, 4e7, 3e8):
        charge = scale * unit + background
        old = ramps.scene_factors(charge, ramp, exptime, FULL_WELL, coefficients, orders, KERNEL, "after", 3)
        new, usable = ramps.scene_factors_coupled(powers, scale, background, ramp, exptime, FULL_WELL, coefficients, orders)
        assert np.array_equal(usable, old.usable)
        assert np.allclose(new.factors, old.factors, rtol=1e-12, atol=0)
        cropped, usable_c = ramps.scene_factors_coupled(
            powers, scale, background, ramp, exptime, FULL_WELL, coefficients, orders, margin=margin
        )
        assert np.array_equal(usable_c, old.usable) and cropped.margin == margin
        assert np.allclose(cropped.factors, old.factors[core], rtol=1e-12, atol=0)
        before = ramps.scene_perturbation(old, BETA, coefficients[1:], KERNEL, "after", 3)
        for sr, pick in ((new, (Ellipsis,)), (cropped, core)):
            after = ramps.scene_perturbation(sr, BETA, coefficients[1:], KERNEL, "after", 3)
            for a, b in zip(after, before, strict=True):
                assert np.allclose(a, b[pick], rtol=1e-11, atol=1e-13 * np.abs(b).max())
        # A per-pixel beta (the scatter) cannot be coupled on a core: the whole stamps are computed.
        betas = BETA * (1 + 0.1 * np.random.default_rng(1).standard_normal(unit.shape))
        whole = ramps.scene_perturbation(cropped, betas, coefficients[1:], KERNEL, "after", 3)[0]
        reference = ramps.scene_perturbation(old, betas, coefficients[1:], KERNEL, "after", 3)[0]
        assert np.allclose(whole, reference, rtol=1e-11, atol=1e-13 * np.abs(reference).max())


def _old_path(powers, scale, background, ramp, exptime_s, full_well_e, state, orders, pick=slice(None), margin=0, region=None):
    """What the Roman scene did before: every read of every pixel coupled, the whole stamps."""
    charge = scale * powers.unit[pick] + background
    sr = ramps.scene_factors(charge, ramp, exptime_s, full_well_e, state, orders, powers.kernel, "after", powers.oversampling)
    return sr, sr.usable


def test_a_roman_table_gives_the_slopes_of_the_old_path(monkeypatch):
    settings = tablebuild.TableSettings.roman(realizations=4)
    config = settings.config("H158", 9, position=(700.0, 3500.0))
    # Bright rows where the ramp drops resultants in the core, one near its limit, faint ones.
    magnitudes = [13.0, 14.5, 16.0, 18.3, 22.0]

    def run():
        scene = experiment.prepare(config)
        return experiment.slopes(config, magnitudes, scene=scene, linearise_at=settings.linearise_at)

    new = run()
    calls = []
    monkeypatch.setattr(ramps, "scene_factors_coupled", lambda *a, **k: calls.append(1) or _old_path(*a, **k))
    old = run()
    assert len(calls) == len(magnitudes)  # the old path did run
    assert any(r.extras["ramp"]["fitted_on_fewer"] for r in old)  # the case includes saturated resultants
    for a, b in zip(new, old, strict=True):
        for name in ("dR_over_R", "de1", "de2"):
            assert a.bias[name].mean == pytest.approx(b.bias[name].mean, rel=1e-6)
            assert a.scatter[name]["value"] == pytest.approx(b.scatter[name]["value"], rel=1e-6)
        assert a.extras["ramp"] == b.extras["ramp"]
