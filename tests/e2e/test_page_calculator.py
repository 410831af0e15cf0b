"""The page in a real headless Chromium (Debian's package), driven by Playwright, against a real server.

Loads the page, solves for each of the three unknowns and checks the answer's point is drawn on the
curve, turns on the paper overlay, exports PNG and CSV, runs a small simulation and watches its
progress reach 100%, and checks a readable error for bad input. Screenshots go to test-artifacts/.
"""

from __future__ import annotations

import csv
import io
import shutil
from pathlib import Path

import pytest

from nlpsf.solve import solver

from .browser import ARTIFACTS, answer_point_is_drawn, solve_for

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.mark.parametrize(
    ("unknown", "given"),
    [
        ("precision", {"tolerance": "1e-4", "magnitude": "18.3"}),
        ("tolerance", {"precision": "0.01", "magnitude": "20"}),
        ("magnitude", {"precision": "0.01", "tolerance": "1e-4"}),
    ],
)
def test_solve_each_unknown_and_see_the_point(page, unknown, given):
    page.evaluate("() => { delete document.getElementById('plot-calc').dataset.point; }")
    solution = solve_for(page, unknown, given)
    assert solution["solved_for"] == unknown
    expected = solver.solve("H158", **{k: float(v) for k, v in given.items()}).to_dict()
    assert solution[unknown] == pytest.approx(expected[unknown], rel=1e-9)
    answer = page.inner_text("[data-testid=solve-answer]")
    assert answer.startswith({"precision": "precision p", "tolerance": "tolerance T", "magnitude": "magnitude m"}[unknown])
    assert "±" in answer or solution["uncertainty"] is None
    # The solved value is written into its field, to the digits its uncertainty allows (precision as a
    # percent), and the conditions are shown with it.
    shown = page.input_value(f"#solve-{unknown}")
    value = float(shown.rstrip(" %")) / 100 if unknown == "precision" else float(shown)
    assert shown.endswith(" %") == (unknown == "precision")
    assert abs(value - expected[unknown]) <= max(expected["uncertainty"] or 0, 0.005 if unknown == "magnitude" else 0) / 2
    conditions = page.inner_text("#solve-result .conditions")
    # The exposure box is left empty: the page sends none, and the answer is the library's default's
    # (the Roman default's HLWAS exposure), which the conditions quote.
    assert page.input_value("#solve-exptime") == ""
    assert f"{expected['exptime']:.4g} s" in conditions and "H158" in conditions and "detector 18" in conditions
    assert solution["fidelity"] == expected["fidelity"] and "method: " in conditions
    assert answer_point_is_drawn(page)
    page.locator("#calculator").screenshot(path=str(ARTIFACTS / f"e2e-solve-{unknown}.png"))


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [("magnitude", "abc", "magnitude"), ("tolerance", "-1", "tolerance"), ("magnitude", "", "magnitude")],
)
def test_bad_input_shows_a_readable_error(page, field, value, words):
    page.check("#solve-for-precision")
    page.fill("#solve-tolerance", "1e-4")
    page.fill("#solve-magnitude", "18.3")
    page.fill(f"#solve-{field}", value)
    page.click("#solve-button")
    error = page.wait_for_selector("#solve-error:not([hidden])")
    text = error.inner_text()
    assert words in text and len(text) > 15
    assert page.get_attribute(f"#solve-{field}", "aria-invalid") == "true"
    page.fill("#solve-magnitude", "18.3")
    page.fill("#solve-tolerance", "1e-4")
    page.click("#solve-button")
    page.wait_for_selector("#solve-error", state="hidden")


def test_curves_paper_overlay_and_exports(page, tmp_path):
    page.check("#paper-overlay")
    page.wait_for_function("() => document.querySelector('#plot-slopes').innerText.includes('(paper)')")
    legend = page.inner_text("#plot-slopes")
    assert "H158 (paper)" in legend and "F184" in legend
    # Hovering shows values in the legend.
    page.wait_for_selector("#plot-slopes .u-over")
    box = page.locator("#plot-slopes .u-over").bounding_box()
    page.mouse.move(box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.5)
    legend = page.inner_text("#plot-slopes .u-legend")
    assert any(ch.isdigit() for ch in legend) and "±" in legend, "hover shows values with their uncertainty"
    with page.expect_download() as png:
        page.click("button[data-png=slopes]")
    path = tmp_path / "slopes.png"
    png.value.save_as(path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    shutil.copy(path, ARTIFACTS / "e2e-export-slopes.png")
    with page.expect_download() as table:
        page.click("button[data-csv=slopes]")
    rows = list(csv.reader(io.StringIO(Path(table.value.path()).read_text()), delimiter=","))
    rows = [row for row in rows if not row[0].startswith("#")]
    assert rows[0][0] == "series" and len(rows) > 50
    for name in ("beta", "sigma"):
        assert page.locator(f"#plot-{name} canvas").count() == 1


def test_simulation_progress_reaches_100_percent(page):
    page.fill("#sim-magnitudes", "18.3, 19")
    page.fill("#sim-betas", "2.5e-7, 5e-7, 1e-6")
    page.fill("#sim-realizations", "40")
    page.fill("#sim-seed", "5")
    page.click("#sim-button")
    seen = []
    for _ in range(1200):
        text = page.inner_text("[data-testid=sim-progress-text]")
        if not seen or seen[-1] != text:
            seen.append(text)
        if text.startswith("100%") and "done" in text:
            break
        page.wait_for_timeout(50)
    assert seen[-1].startswith("100%"), seen
    assert len(seen) >= 2, f"the progress bar should move: {seen}"
    assert page.eval_on_selector("#sim-progress", "p => p.value") == 1
    # The worker reports 100 % "done" a moment before the job's result is stored and fetched.
    page.wait_for_function("() => document.querySelectorAll('#sim-table tbody tr').length > 0", timeout=30_000)
    rows = page.locator("#sim-table tbody tr")
    assert rows.count() == 6
    assert "fresh simulation" in page.inner_text("#sim-conditions")
    # Fresh points join the metric-vs-beta plot.
    page.wait_for_function("() => document.querySelector('#plot-beta').innerText.includes('fresh simulation')")
    # The points are the simulation's own question (no scene ticked: the Roman default, up its ramp),
    # not the paper's table line they are drawn on: the captions say so.
    for caption in ("#beta-caption", "#sigma-caption"):
        text = page.inner_text(caption)
        if "fresh simulation" in page.inner_text(f"#plot-{caption[1:].split('-')[0]}"):
            assert "the simulation's own question (scene: " in text and "SED k0v" in text and "up the ramp" in text, text
    page.locator("#simulation").screenshot(path=str(ARTIFACTS / "e2e-simulation.png"))


def test_simulation_limits_are_reported(page):
    # Over this deployment's cap (max_realizations, 2,000 by default) but inside the library's range:
    # the answer names the deployment's limit.
    page.fill("#sim-realizations", "5000")
    page.click("#sim-button")
    error = page.wait_for_selector("#sim-error:not([hidden])")
    assert "realizations" in error.inner_text() and "max_realizations" in error.inner_text()
    assert page.get_attribute("#sim-realizations", "aria-invalid") == "true"
    page.fill("#sim-realizations", "20")


def canvas_colour_at(page, plot: str, x_value: float, y_fraction: float) -> list[int]:
    """RGB of plot's canvas at data x = x_value, a fraction of the way down the plotting area."""
    return page.evaluate(
        """([plot, xv, fy]) => {
            const u = state.plots[plot];
            const x = Math.round(u.valToPos(xv, "x", true));
            const y = Math.round(u.bbox.top + fy * u.bbox.height);
            return Array.from(u.ctx.getImageData(x, y, 1, 1).data.slice(0, 3));
        }""",
        [plot, x_value, y_fraction],
    )


def test_ramp_choice_in_the_calculator_draws_both_saturation_limits(page):
    # The paper's ramp physics: the paper's scene over its 168.1 s final frame.
    page.select_option("#solve-scene", "paper")
    page.fill("#solve-exptime", "168.1")
    page.select_option("#solve-readout", "uniform")
    page.fill("#solve-ramp", "8")
    solution = solve_for(page, "magnitude", {"precision": "0.01", "tolerance": "1e-4"})
    assert solution["conditions"]["ramp"]["ma_table"] == "uniform-8"
    expected = solver.solve("H158", precision=0.01, tolerance=1e-4, ramp=solver.ramps.Ramp.uniform(8, 168.1), preset="paper")
    assert solution["magnitude"] == pytest.approx(expected.magnitude, rel=1e-9)
    # The ramp's limit is the resultant a slope needs: the second of 8 uniform reads, at 2 T / 8.
    text = page.inner_text("#solve-result")
    assert "second resultant" in text and f"{2 * 168.1 / 8:.4g} s" in text and "first resultant" not in text
    # One saturation story: the ramp's limit binds (the shaded range ends there), the final frame's is a
    # line named as such. The plot is redrawn after the answer arrives (its curves are one more request).
    limits = [solution["saturation_magnitude"], solution["final_frame_saturation_magnitude"]]
    page.wait_for_function(
        """(want) => {
            const e = state.exports.calc;
            const shade = e?.shades?.[0]?.to, line = e?.markers?.[0]?.x;
            if (shade === undefined || line === undefined) return false;
            return Math.abs(shade - want[0]) < 1e-9 && Math.abs(line - want[1]) < 1e-9;
        }""",
        arg=limits,
    )
    assert "up the ramp" in page.evaluate("() => state.exports.calc.shades[0].label")
    assert "final frame's limit" in page.evaluate("() => state.exports.calc.markers[0].label")
    # The final frame's limit is a dashed grey line on the canvas (a dash is 6 px of 10: a few heights).
    line = page.evaluate("() => state.exports.calc.markers[0].x")
    final_frame = [canvas_colour_at(page, "calc", line, f) for f in (0.3, 0.35, 0.4, 0.45, 0.5)]
    assert any(abs(r - g) < 20 and r < 140 for r, g, _ in final_frame)
    # The curve is this ramp's own, from the tables where they map it exactly (OLS, no resultant
    # dropped): there it is the solver's tolerance answer at the answer's precision.
    curve = page.evaluate("() => state.exports.calc.columns[0]")
    m = next(x for x, y in zip(curve["x"], curve["y"], strict=True) if y is not None and x > limits[1] + 0.5)
    there = solver.solve("H158", precision=1.0, magnitude=m, ramp=solver.ramps.Ramp.uniform(8, 168.1), preset="paper")
    assert curve["y"][curve["x"].index(m)] == pytest.approx(abs(there.slope), rel=1e-9)
    page.locator("#calculator").screenshot(path=str(ARTIFACTS / "e2e-solve-ramp.png"))
    # An MA table takes its own exposure; going back to the final frame empties the box (the API
    # fills the scene's exposure, which the placeholder names: the paper's 168.1 s here).
    page.select_option("#solve-readout", "table:romanisim-109")
    assert float(page.input_value("#solve-exptime")) == pytest.approx(133.76)
    page.select_option("#solve-readout", "final")
    assert page.input_value("#solve-exptime") == ""
    assert "168.1" in page.get_attribute("#solve-exptime", "placeholder")
    assert page.is_disabled("#solve-ramp") and page.is_disabled("#solve-ramp_fit")
    page.select_option("#solve-scene", "")  # back to the Roman default for the module's later tests
    assert "139.1" in page.get_attribute("#solve-exptime", "placeholder")


def test_ramp_choice_in_a_fresh_simulation(page):
    page.fill("#sim-magnitudes", "17")
    page.fill("#sim-betas", "5e-7")
    page.fill("#sim-realizations", "10")
    page.select_option("#sim-readout", "table:romanisim-110")
    page.select_option("#sim-ramp_fit", "optimal")
    page.click("#sim-button")
    # The job's progress can reach 1 a poll before its status is done: wait for the shown result.
    page.wait_for_function("() => document.getElementById('sim-conditions').innerText.includes('romanisim-110')", timeout=120_000)
    conditions = page.inner_text("#sim-conditions")
    assert "up the ramp: romanisim-110" in conditions and "optimally weighted" in conditions
    assert "fitted on fewer than 16 resultants" in page.inner_text("#sim-table")
    page.select_option("#sim-readout", "final")
