"""Official backgrounds and noise: presets, scaling, and the issue's K213 number."""

import math

import pytest

from nlpsf import defaults, roman
from nlpsf.checks import InputError
from nlpsf.roman import backgrounds


def test_presets_add_up_and_scale_with_exposure():
    for band in roman.BANDS:
        b = backgrounds.background("roman-typical", band, 7, 100.0)
        assert b.total_e == pytest.approx(b.zodiacal_e + b.thermal_e + b.dark_e, rel=1e-15)
        assert backgrounds.background("roman-typical", band, 7, 200.0).total_e == pytest.approx(2 * b.total_e, rel=1e-12)
        assert backgrounds.background("none", band, 7, 100.0).total_e == 0.0
        # The typical sky is the official sensitivity tables' twice-minimum zodiacal light.
        minimum = backgrounds.background("roman-minimum", band, 7, 100.0)
        assert b.zodiacal_e == pytest.approx(2 * minimum.zodiacal_e, rel=1e-12)
        assert b.thermal_e == minimum.thermal_e and b.dark_e == minimum.dark_e


def test_k213_thermal_background_is_the_issue_s_740_electrons_and_moves_saturation():
    b = backgrounds.background("roman-typical", "K213", 18, defaults.EXPTIME_S)
    assert b.thermal_e == pytest.approx(740, rel=0.01)  # 4.38 e-/s x 168.1 s
    assert b.thermal_e > 10 * (b.zodiacal_e + b.dark_e)  # thermal dominates K213, unlike every blue band
    assert backgrounds.background("roman-typical", "H158", 18, 168.1).thermal_e < 10
    shift = backgrounds.saturation_shift_mag(b.total_e, defaults.FULL_WELL_E)
    # A background that fills a fraction f of the well saturates stars -2.5 log10(1 - f) fainter.
    assert shift == pytest.approx(2.5 / math.log(10) * b.total_e / 1.1e5, rel=0.01)
    assert 0.005 < shift < 0.01


def test_read_noise_is_the_cds_noise_of_one_read():
    for sca in range(1, 19):
        assert backgrounds.read_noise(sca) * math.sqrt(2) == pytest.approx(backgrounds.cds_noise(sca), rel=1e-12)
        # A 55-read ramp fit averages the read noise down: its total noise is well below one CDS pair's.
        assert backgrounds.total_noise(sca) < backgrounds.cds_noise(sca)
        assert 0 < backgrounds.dark_rate(sca) < 0.05  # the requirement the summary table counts against


@pytest.mark.parametrize(
    ("name", "column"),
    [
        ("WFI_CDS_Noise_summary.ecsv", "CDS Noise - Median"),
        ("WFI_Dark_current_summary.ecsv", "Dark Current - Median"),
        ("WFI_Total_noise.ecsv", "Total noise - median"),
    ],
)
def test_per_sca_summaries_read_as_astropys_ecsv_reader_reads_them(name, column):
    # The per-SCA tables are read with the standard library (no astropy import for a ramp's read
    # noise); astropy's ECSV reader is the independent reading.
    from astropy.table import Table

    table = Table.read(roman.official_data_dir() / name, format="ascii.ecsv")
    by_scu = {int(str(u)): float(v) for u, v in zip(table[table.colnames[0]], table[column], strict=True) if str(u).isdigit()}
    assert backgrounds._per_sca(name, column) == tuple(by_scu[s] for s in range(1, 19))


def test_a_ramps_default_read_noise_imports_no_astropy():
    import subprocess
    import sys

    code = "import sys; from nlpsf.sim import ramps; ramps.build(6, fit='optimal', sca=3); print('astropy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_bad_background_input_names_its_field():
    with pytest.raises(InputError, match="background"):
        backgrounds.background("moonlight", "H158", 1, 100.0)
    with pytest.raises(InputError, match="exptime"):
        backgrounds.background("roman-typical", "H158", 1, 0.0)
    with pytest.raises(InputError, match="zodiacal_factor"):
        backgrounds.zodiacal_rate("H158", -1.0)
    with pytest.raises(InputError, match="background"):
        backgrounds.saturation_shift_mag(1.1e5, 1.1e5)


def test_a_scene_background_is_a_preset_name_or_electrons():
    typical = backgrounds.background("roman-typical", "K213", 5, 100.0).total_e
    assert backgrounds.resolve("roman-typical", "K213", 5, 100.0) == typical
    assert backgrounds.resolve("120", "K213", 5, 100.0) == 120.0
    assert backgrounds.resolve(0.0, "K213", 5, 100.0) == 0.0
    for bad in ("moonlight", -1.0, "nan"):
        with pytest.raises(InputError, match="background"):
            backgrounds.resolve(bad, "K213", 5, 100.0)
