"""The page after the default switch (issue 17): the calculator answers the Roman default unless the
paper's scene is chosen, sends the exposure only when one is typed (the API fills the scene's), carries
the scene in the shareable URL, and says the curves are the paper's tables. Expected answers are the
library's for the same request, never the page's own."""

from __future__ import annotations

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.slopes import tables
from nlpsf.solve import solver

from .browser import ARTIFACTS

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

QUESTION = {"tolerance": "1e-4", "magnitude": "18.3"}


def solve_sent(page) -> tuple[dict, dict]:
    """(the body the page sent, the answer it showed) for one click of Solve."""
    page.evaluate("() => { state.lastSolution = undefined; }")
    page.check("#solve-for-precision")
    for name, value in QUESTION.items():
        page.fill(f"#solve-{name}", value)
    with page.expect_request(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as request:
        page.click("#solve-button")
    page.wait_for_function("() => state.lastSolution !== undefined", timeout=240_000)
    return request.value.post_data_json, page.evaluate("() => state.lastSolution")


def test_the_scene_choice_is_sent_shown_and_shared(page, server):
    # The first view: the Roman default, its exposure named from the API, the box left empty.
    assert page.input_value("#solve-scene") == "" and page.input_value("#solve-exptime") == ""
    assert f"{roman_default.exptime_s():.6g}" in page.get_attribute("#solve-exptime", "placeholder")
    # The slopes of every band are the calculator's question's: the Roman default, over the SCA.
    note = page.inner_text("[data-testid=curves-scene-note]")
    assert "Roman default" in note and "anywhere on the SCA" in note
    # Each band has its own sky and field-grid nodes: each band's are said, none stated for all.
    page.wait_for_function("() => document.getElementById('curves-scene-text').textContent.includes('each band at its own')")
    note = page.inner_text("[data-testid=curves-scene-note]")
    for band in tables.load_tables().bands:
        own = solver.solve(band, tolerance=1e-4, magnitude=18.3).to_dict()["conditions"]
        assert f"{band} background {own['scene']['background_e']:.3g} e⁻, {len(own['sca_range']['nodes'])} nodes" in note, band
    sent, answer = solve_sent(page)
    assert "scene" not in sent and "exptime" not in sent
    truth = solver.solve("H158", tolerance=1e-4, magnitude=18.3)
    assert answer["precision"] == pytest.approx(truth.precision, rel=1e-9)
    assert answer["exptime"] == pytest.approx(roman_default.exptime_s(), rel=1e-12)
    line = page.inner_text("[data-testid=scene-line]")
    # The library's description without the node it reports (no position was given: the answer holds
    # anywhere on the SCA), its numbers to the digits they support.
    described = truth.to_dict()["conditions"]["scene_description"]
    assert "Roman default" in line and "anywhere on the SCA" in line and "position" not in line
    assert described.split("SED ", 1)[1].split(", background")[0] in line
    page.screenshot(path=str(ARTIFACTS / "e2e-default-answer.png"), full_page=False)
    # "Use the paper's scene" chooses it and answers again: the paper's numbers over its 168.1 s.
    page.evaluate("() => { state.lastSolution = undefined; }")
    page.click("#use-paper-scene")
    page.wait_for_function("() => state.lastSolution !== undefined", timeout=240_000)
    assert page.input_value("#solve-scene") == "paper"
    paper = solver.solve("H158", tolerance=1e-4, magnitude=18.3, preset="paper")
    assert page.evaluate("() => state.lastSolution.precision") == pytest.approx(paper.precision, rel=1e-9)
    assert "168.1 s" in page.inner_text("#solve-result .conditions")
    assert "the paper's scene" in page.inner_text("[data-testid=scene-line]")
    # The link carries the scene; opening it restores the choice and the paper's answer.
    url = page.url
    assert "scene=paper" in url
    page.goto(server)
    page.wait_for_selector("body[data-ready='true']")
    assert page.input_value("#solve-scene") == ""
    page.goto(url)
    page.wait_for_selector("body[data-ready='true']")
    page.wait_for_selector("[data-testid=solve-answer]")
    assert page.input_value("#solve-scene") == "paper"
    assert "168.1" in page.get_attribute("#solve-exptime", "placeholder")
    sent, answer = solve_sent(page)
    assert sent["scene"] == "paper" and "exptime" not in sent
    assert answer["precision"] == pytest.approx(paper.precision, rel=1e-9)
    # A typed exposure is sent as typed.
    page.fill("#solve-exptime", "150")
    sent, answer = solve_sent(page)
    assert sent["exptime"] == 150
    assert answer["precision"] == pytest.approx(
        solver.solve("H158", tolerance=1e-4, magnitude=18.3, preset="paper", exptime=150).precision, rel=1e-9
    )
    page.fill("#solve-exptime", "")
    page.select_option("#solve-scene", "")


def test_the_answer_shows_its_conservative_bound_and_the_star_colour_range(page):
    # The library's conservative bound and SED range for the same request, shown in the headline's unit.
    _, answer = solve_sent(page)
    truth = solver.solve("H158", tolerance=1e-4, magnitude=18.3).to_dict()
    bound = truth["conservative"]
    assert answer["conservative"]["precision"] == pytest.approx(bound["precision"], rel=1e-9)
    line = page.inner_text("[data-testid=conservative-line]")
    assert f"{bound['precision'] * 100:.3g} %" in line and "95 %" in line
    assert bound["precision"] < truth["precision"]  # a larger slope bound asks for a finer precision
    ranges = page.locator("[data-testid=range-line]").all_inner_texts()
    sed = next(text for text in ranges if text.startswith("star colour"))
    for end, value in zip(truth["ranges"]["sed"]["ends"], truth["ranges"]["sed"]["precision"], strict=True):
        assert f"{value * 100:.3g} % at {end.replace('blackbody:', 'blackbody ')}" in sed
    assert "not an uncertainty" in sed
    page.locator("#solve-result").screenshot(path=str(ARTIFACTS / "e2e-default-bound-and-ranges.png"))
