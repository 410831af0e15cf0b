"""Issue 11's page in headless Chromium: the requirement plot and its hover, several fresh simulations
at different beta all drawn, a failed solve clearing the answer, every bad field reported at once, and
the page at 420 px wide with no sideways scroll and every input reachable."""

from __future__ import annotations

import pytest

from nlpsf.solve import solver

from .browser import ARTIFACTS, answer_point_is_drawn, solve_for

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def test_requirement_plot_hover_reads_the_requirement(page):
    # The plot's curves are the shipped tables' (the paper's scene): its answer is on them there.
    page.select_option("#solve-scene", "paper")
    # The first view's answer (the Roman default's) is drawn already: wait for this answer's plot.
    page.evaluate("() => { delete document.getElementById('plot-req').dataset.answer; }")
    solve_for(page, "precision", {"tolerance": "1e-4", "magnitude": "19"})
    page.wait_for_function("() => document.getElementById('plot-req').dataset.answer === 'shown'")
    labels = page.evaluate("() => state.exports.req.columns.map((c) => c.label)")
    assert sum(label.startswith("T = ") for label in labels) == 5 and "T = 1e-4 (chosen)" in labels
    # One saturation story: the answer's own limit (the paper's final frame here), named as such.
    shades = page.evaluate("() => state.exports.req.shades.map((s) => [s.label, s.to])")
    saturation = page.evaluate("() => state.lastSolution.saturation_magnitude")
    assert shades[0][1] == pytest.approx(saturation, abs=1e-12) and "saturated in the final frame" in shades[0][0]
    # Before any hover the legend shows numbers, not dashes.
    legend = page.inner_text("#plot-req .u-legend")
    assert "–" not in legend and any(ch.isdigit() for ch in legend)
    # The plot may be redrawn once more after the answer (its curves are a second request): wait for it.
    over = page.locator("#plot-req .u-over")
    box = None
    for _ in range(50):  # a redraw replaces the element between the wait and the measurement
        over.wait_for(state="visible")
        box = over.bounding_box()
        if box is not None:
            break
        page.wait_for_timeout(100)
    assert box is not None
    page.mouse.move(box["x"] + box["width"] * 0.7, box["y"] + box["height"] * 0.5)
    page.wait_for_function("() => document.getElementById('req-readout').dataset.magnitude !== undefined")
    readout = page.locator("#req-readout")
    magnitude = float(readout.get_attribute("data-magnitude"))
    precision = float(readout.get_attribute("data-precision"))
    # The curve point is a table magnitude: the solver at that magnitude gives the same requirement.
    expected = solver.solve("H158", tolerance=1e-4, magnitude=magnitude, preset="paper").precision
    assert precision == pytest.approx(expected, rel=1e-6)
    text = readout.inner_text()
    assert "statistical" in text and "method" in text and "T = 1e-4" in text
    legend = page.inner_text("#plot-req .u-legend")
    assert "stat" in legend and "method" in legend, "hover gives both uncertainties"
    page.locator("#calculator").screenshot(path=str(ARTIFACTS / "e2e-requirement.png"))
    with page.expect_download() as png:
        page.click("button[data-png=req]")
    path = ARTIFACTS / "e2e-export-requirement.png"
    png.value.save_as(path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page.select_option("#solve-scene", "")  # the Roman default again for the module's later tests


def test_magnitude_answer_names_the_binding_limit(page):
    solution = solve_for(page, "magnitude", {"precision": "0.01", "tolerance": "1e-4"})
    assert solution["binding_limit"] in ("saturation", "nonlinearity")
    text = page.inner_text("[data-testid=binding-limit]")
    assert ("saturation binds" in text) == (solution["binding_limit"] == "saturation")


def test_a_failed_solve_clears_the_marker(page):
    solve_for(page, "precision", {"tolerance": "1e-4", "magnitude": "18.3"})
    assert answer_point_is_drawn(page)
    page.fill("#solve-magnitude", "11")  # valid text, refused by the server: past the ramp's bright margin
    with page.expect_response(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as response:
        page.click("#solve-button")
    assert response.value.status == 422
    page.wait_for_selector("#solve-error:not([hidden])")
    # The refused question's own curves are drawn after the refusal (one more request).
    page.wait_for_function("() => ['req', 'calc'].every((p) => document.getElementById(`plot-${p}`).dataset.answer === 'none')")
    for plot in ("req", "calc"):
        assert page.get_attribute(f"#plot-{plot}", "data-answer") == "none"
        assert page.evaluate(f"() => state.exports.{plot}.columns.some((c) => c.answer)") is False
    # The earlier answer stays, greyed, saying what it answered; pin and downloads are off.
    assert "m = 18.3" in page.inner_text("[data-testid=stale-note]") and "stale" in page.get_attribute("#solve-result", "class")
    assert page.is_disabled("#pin-answer") and page.is_disabled("#download-json")
    # The legends read nothing (no value left at the refused answer's magnitude) until hovered.
    for plot in ("req", "calc"):
        values = page.locator(f"#plot-{plot} .u-legend .u-value").all_inner_texts()
        assert values and all(v == "–" for v in values), values
        assert "legend-void" in page.get_attribute(f"#plot-{plot}", "class")
    page.fill("#solve-magnitude", "18.3")
    solve_for(page, "precision", {"tolerance": "1e-4", "magnitude": "18.3"})
    page.wait_for_function("() => document.getElementById('plot-req').dataset.answer === 'shown'")
    assert "18.3" in page.inner_text("#plot-calc .u-legend")
    assert "legend-void" not in (page.get_attribute("#plot-calc", "class") or "")


def test_every_bad_field_is_reported_at_once(page):
    page.check("#solve-for-precision")
    page.fill("#solve-beta0", "five")
    page.fill("#solve-exptime", "long")  # empty is no error: the API fills the scene's exposure
    page.fill("#solve-tolerance", "1e-4")
    page.fill("#solve-magnitude", "abc")
    page.click("#solve-button")
    error = page.wait_for_selector("#solve-error:not([hidden])")
    items = [li.get_attribute("data-field") for li in error.query_selector_all("li")]
    assert set(items) == {"beta0", "exptime", "magnitude"}
    for field in ("beta0", "exptime", "magnitude"):
        assert page.get_attribute(f"#solve-{field}", "aria-invalid") == "true"
    page.fill("#solve-beta0", "5e-7")
    page.fill("#solve-exptime", "")
    page.fill("#solve-magnitude", "18.3")
    page.click("#solve-button")
    page.wait_for_selector("#solve-error", state="hidden")


def test_fresh_simulations_at_several_betas_are_all_shown(page):
    page.fill("#sim-magnitudes", "18.3")
    page.fill("#sim-betas", "2.5e-7, 5e-7, 1e-6")
    page.fill("#sim-sigma_betas", "2e-8, 5e-8")
    page.fill("#sim-realizations", "6")
    page.fill("#sim-seed", "11")
    page.select_option("#sim-fidelity", "linear")
    page.click("#sim-button")
    page.wait_for_function("() => document.querySelector('#plot-sigma').innerText.includes('fresh simulation')", timeout=180_000)
    labels = page.evaluate("() => state.exports.sigma.columns.map((c) => c.label)")
    fresh = [label for label in labels if label.startswith("fresh simulation")]
    assert len(fresh) == 3 and all(f"β = {b}" in " ".join(fresh) for b in ("2.5e-7", "5e-7", "1e-6"))
    points = page.evaluate("() => state.exports.sigma.columns.filter((c) => c.label.startsWith('fresh')).map((c) => c.x.length)")
    assert points == [2, 2, 2]
    assert "3 series" in page.inner_text("#sigma-caption")
    # Each scatter point has its error bar drawn, the API's std_error: std / sqrt(2 (n - 1)) over the
    # n = 6 beta-map draws (the standard error of a normal sample's standard deviation).
    whiskers = page.evaluate("() => state.plots.sigma.whiskers")
    rows = page.evaluate("() => state.lastSimulation.results.filter((r) => r.sigma_beta > 0)")
    assert len(whiskers) == len(rows) == 6
    expected = sorted(r["dR_over_R"]["std"] / (2 * (6 - 1)) ** 0.5 for r in rows)
    assert sorted(w["half"] for w in whiskers) == pytest.approx(expected, rel=1e-9)
    page.locator("#curves").screenshot(path=str(ARTIFACTS / "e2e-sigma-betas.png"))
    page.fill("#sim-sigma_betas", "0")
    page.select_option("#sim-fidelity", "monte_carlo")


def test_the_page_at_420_px(page):
    page.set_viewport_size({"width": 420, "height": 900})
    try:
        page.wait_for_timeout(400)  # the plots resize after 150 ms
        overflow = page.evaluate("() => document.documentElement.scrollWidth - document.documentElement.clientWidth")
        assert overflow <= 0, f"the page scrolls sideways by {overflow} px"
        controls = page.evaluate(
            """() => Array.from(document.querySelectorAll('main input, main select, main button'))
                .filter((el) => el.offsetParent !== null)
                .map((el) => { const r = el.getBoundingClientRect();
                    return { id: el.id || el.name || el.textContent, left: r.left, right: r.right,
                        width: ["checkbox", "radio"].includes(el.type) ? 99 : r.width }; })"""
        )
        assert len(controls) > 40
        cut = [c for c in controls if c["left"] < 0 or c["right"] > 420 or c["width"] < 20]
        assert not cut, f"controls cut off at 420 px: {cut}"
        page.fill("#solve-magnitude", "18.3")  # reachable and usable
        page.screenshot(path=str(ARTIFACTS / "e2e-420px.png"), full_page=True)
    finally:
        page.set_viewport_size({"width": 1280, "height": 1000})


def test_a_shear_budget_takes_the_place_of_the_tolerance(page):
    page.check("#solve-for-precision")
    page.fill("#solve-magnitude", "19")
    page.fill("#solve-shear_m", "2e-3")
    page.fill("#solve-size_ratio", "1.5")
    with page.expect_request(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as request:
        page.click("#solve-button")
    sent = request.value.post_data_json
    assert sent["shear_m"] == 2e-3 and sent["size_ratio"] == 1.5 and "tolerance" not in sent
    page.wait_for_selector("[data-testid=shear]")
    expected = solver.solve("H158", magnitude=19, shear_m=2e-3, size_ratio=1.5)
    assert f"T = {expected.tolerance:.4g}" in page.inner_text("[data-testid=shear]").replace("e-0", "e-")
    page.fill("#solve-shear_m", "")
    page.fill("#solve-size_ratio", "")
    page.fill("#solve-tolerance", "1e-4")
    page.click("#solve-button")
    page.wait_for_selector("#solve-error", state="hidden")


def test_each_flag_on_an_answer_opens_its_meaning_by_keyboard(page):
    from nlpsf import flags

    # m = 17 saturates the paper's final frame (the Roman default's ramp reads it before it does).
    page.select_option("#solve-scene", "paper")
    solution = solve_for(page, "tolerance", {"precision": "0.5", "magnitude": "17"})
    page.select_option("#solve-scene", "")
    assert "star_saturated" in solution["flag_codes"]
    items = page.locator("[data-testid=answer-flags] li")
    assert items.count() == len(solution["flags"])
    index = solution["flag_codes"].index("star_saturated")
    summary = items.nth(index).locator("summary")
    summary.focus()
    page.keyboard.press("Enter")
    details = items.nth(index).locator("details")
    assert details.get_attribute("open") is not None
    meaning = {entry["code"]: entry["meaning"] for entry in flags.catalogue()}["star_saturated"]
    assert items.nth(index).locator("[data-flag-code=star_saturated]").inner_text() == meaning


def test_the_effect_explanations_list_the_registrys_effects(page):
    from nlpsf.sim import scene as scenes

    terms = page.locator("#effect-explanations dt").all_inner_texts()
    # One per registry effect (in the page's words), then the pupil-scale rule.
    assert len(terms) == len(scenes.REGISTRY) + 1
    text = page.evaluate("() => document.getElementById('effect-explanations').textContent")
    assert f"jitter_arcsec = {scenes.ROMAN_JITTER_ARCSEC:g}" in text
