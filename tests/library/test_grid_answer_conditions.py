"""An answer read from the Roman default's field grid quotes the grid's settings, not the paper tables'.

The paper tables were built at the SCA centre with the ``galsim`` pupil rule over a 168.1 s final
frame; the grid's nodes with the ``official`` rule (issue 17: the rule that reproduces the official
clear areas) over the HLWAS ramp. An answer that read the grid must say the latter.
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.slopes import fieldgrid
from nlpsf.solve import solver


@pytest.mark.parametrize("band, sca", [("H158", 18), ("W146", 6)])
def test_a_grid_answer_names_the_grids_pupil_rule_and_exposure(band, sca):
    scene = replace(roman_default.base_scene(), position=(1000.0, 3000.0))
    answer = solver.solve(band, sca, magnitude=19.0, tolerance=1e-4, scene=scene)
    conditions = answer.conditions
    assert conditions["fidelity"] == "table" and "field grid" in conditions["slopes_from"]
    settings = fieldgrid.shipped_grid().conditions(band, sca)["settings"]
    assert conditions["pupil_scale"] == settings["pupil_scale"] == "official"
    assert conditions["table_conditions"]["exptime_s"] == pytest.approx(settings["exptime_s"])
    assert conditions["table_conditions"]["exptime_s"] != pytest.approx(168.1)
    assert conditions["realizations"] == settings["realizations"]
