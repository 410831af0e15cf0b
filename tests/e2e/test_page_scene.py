"""The page's scene section in headless Chromium: the impact report as a bar chart, scene errors named."""

from __future__ import annotations

import pytest

from .browser import ARTIFACTS

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def test_impact_bar_chart_and_scene_errors(page):
    page.fill("#solve-magnitude", "19")
    page.fill("#scene-jitter", "0.02")
    with page.expect_response(lambda r: r.url.endswith("/api/v1/impact"), timeout=180_000) as response:
        page.click("#impact-button")
    assert response.value.status == 200, response.value.text()
    page.wait_for_selector("[data-testid=impact-bars] .bar-row")
    assert page.locator("#impact-bars .bar-row").count() == 8
    assert "(on)" in page.inner_text("#impact-bars [data-effect=jitter]")
    assert "not measured" in page.inner_text("#impact-bars [data-effect=brighter_fatter]")
    page.locator("#scene").screenshot(path=str(ARTIFACTS / "e2e-impact.png"))
    page.fill("#scene-jitter", "-1")
    page.click("#impact-button")
    error = page.wait_for_selector("#scene-error:not([hidden])")
    assert "jitter" in error.inner_text()
    assert page.get_attribute("#scene-jitter", "aria-invalid") == "true"
    page.fill("#scene-jitter", "")
