"""The impact report under another pupil-mask scale rule (``--pupil-scale`` on every simulating
command): its runs use that rule, so the slopes equal a direct simulation with it."""

import pytest

from nlpsf import cli
from nlpsf.checks import InputError
from nlpsf.sim import experiment
from nlpsf.solve import impact


def test_the_impact_report_simulates_with_the_pupil_rule_asked_for():
    report = impact.impact("H158", 18, 19.0, realizations=4, pupil_scale="official")
    assert report["conditions"]["pupil_scale"] == "official"
    config = experiment.SimulationConfig(band="H158", sca=18, realizations=4, method="linear", pupil_scale="official")
    direct = experiment.slopes(config, [19.0], beta0=report["conditions"]["beta0"])[0]
    size, _ = direct.slope("bias", ("dR_over_R",))
    assert report["conditions"]["plain_slope"]["size"] == pytest.approx(size, rel=1e-12)
    galsim = impact.impact("H158", 18, 19.0, realizations=4)
    # SCA 18's official clear area is 9 % larger than the galsim rule's (docs/optics.md): the slopes differ.
    assert abs(galsim["conditions"]["plain_slope"]["size"] / size - 1) > 0.01
    with pytest.raises(InputError, match="pupil_scale"):
        impact.impact("H158", 18, 19.0, realizations=4, pupil_scale="wide")


def test_the_impact_command_takes_the_pupil_rule(capsys):
    assert cli.main(["impact", "--realizations", "2", "--pupil-scale", "header", "--json", "--quiet"]) == 0
    assert '"pupil_scale": "header"' in capsys.readouterr().out
