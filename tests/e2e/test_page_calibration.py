"""The page's calibration section (static/calibration.js) in headless Chromium: K(Q) of the calculator's star
with its signal range, saturation and full-well marks, the ECSV download, a residual's bias, a refusal in plain
words, the phone width and axe-core. Expected numbers come from the library (``nlpsf.calibration`` on the same
request), never from the page's own output."""

from __future__ import annotations

import pytest

from .browser import ARTIFACTS

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

STAR = {"band": "H158", "sca": 7, "magnitude": 19.0, "position": (900.0, 3100.0)}


@pytest.fixture(scope="module")
def library():
    """The same star's response, straight from the library (as ``nlpsf kernel`` computes it)."""
    from nlpsf.calibration import requirement, star_response
    from nlpsf.request.resolve import SolveRequest

    request = SolveRequest.from_json(
        {"band": "H158", "sca": 7, "magnitude": 19.0, "precision": 0.01, "scene": {"position": list(STAR["position"])}}
    )
    response = star_response(requirement.scene_for(request), 19.0, request.beta0)
    return response, response.kernel()


def calculator_star(page):
    page.select_option("#solve-band", STAR["band"])
    page.select_option("#solve-sca", str(STAR["sca"]))
    page.fill("#solve-magnitude", "19")
    where = "#solve-position" if page.locator("#solve-position").count() else "#scene-position"
    page.fill(where, "900,3100")


def test_the_kernel_of_the_calculators_star_is_drawn_with_its_signal_range(page, server, library, tmp_path):
    from astropy.table import Table

    _, kernel = library
    calculator_star(page)
    assert "H158, SCA 7, m = 19, at (900, 3100)" in page.inner_text("[data-testid=kernel-star]")
    with page.expect_response(lambda r: r.url.endswith("/api/v1/calibration/kernel")) as answer:
        page.click("#kernel-button")
    assert answer.value.status in (200, 202), answer.value.text()
    page.wait_for_selector("#kernel-result:not([hidden])", timeout=240_000)
    plot = page.locator("#plot-kernel")
    assert plot.get_attribute("data-metric") == "size"
    bins = kernel.fractional_bins()
    assert int(plot.get_attribute("data-bins")) == bins["size"].size
    assert page.locator("#kernel-table tbody tr").count() == bins["size"].size
    low, high = kernel.signal_range("size")
    assert float(plot.get_attribute("data-signal-low")) == pytest.approx(low, rel=1e-9)
    assert float(plot.get_attribute("data-signal-high")) == pytest.approx(high, rel=1e-9)
    key = page.inner_text("#key-kernel")
    assert "full well: 1.1e5 e⁻ of signal" in key and "saturation" in key and "90 %" in key
    slope = kernel.integrate(lambda q: -(q**2))["size"][0]
    assert f"{slope:.4g}"[:5] in page.inner_text("[data-testid=kernel-summary]")
    # Another PSF quantity redraws from the same answer.
    page.select_option("#kernel-metric", "e")
    assert float(plot.get_attribute("data-signal-low")) == pytest.approx(kernel.signal_range("e")[0], rel=1e-9)
    page.select_option("#kernel-metric", "size")
    # The arrow keys read values.
    plot.focus()
    page.keyboard.press("End")
    readout = page.inner_text("#kernel-readout")
    start, value = readout.split("–")[0].removeprefix("Q = "), readout.split("changes by ")[1].split(" ±")[0]
    assert float(start) == pytest.approx(bins["edges_e"][-2], rel=1e-3)
    assert float(value) == pytest.approx(bins["size"][-1], rel=1e-3)
    # The ECSV download is the CLI's table.
    with page.expect_download() as download:
        page.click("#kernel-ecsv")
    path = tmp_path / download.value.suggested_filename
    download.value.save_as(path)
    assert download.value.suggested_filename == "nlpsf-kernel-H158-sca7-m19.ecsv"
    table = Table.read(path, format="ascii.ecsv")
    assert table.colnames == list(kernel.table().colnames)
    assert table["size"][100] == pytest.approx(kernel.density()["size"][0][100], rel=1e-12)
    for width in (1440, 390):
        page.set_viewport_size({"width": width, "height": 1000})
        page.wait_for_timeout(300)  # the plot follows the window's width
        assert page.evaluate("() => document.scrollingElement.scrollWidth <= window.innerWidth"), width
        page.locator("#calibration").screenshot(path=str(ARTIFACTS / f"e2e-calibration-{width}.png"))
    page.set_viewport_size({"width": 1280, "height": 1000})


def test_a_residual_reports_its_bias_and_a_refusal_is_in_plain_words(page, server, library):
    from nlpsf.calibration import residuals

    response, _ = library
    calculator_star(page)
    page.select_option("#residual-kind", "polynomial")
    page.fill("#residual-polynomial", "0, 0, 0, 2e-14")
    page.click("#residual-button")
    page.wait_for_selector("#residual-result:not([hidden]):not(.stale)", timeout=240_000)
    expected = response.integrate(residuals.from_polynomial([0.0, 0.0, 0.0, 2e-14]))
    for metric in ("size", "e1", "e2", "e"):
        shown = float(page.inner_text(f"[data-testid=bias-{metric}]"))
        assert shown == pytest.approx(expected[metric][0], rel=1e-4), metric
    assert "polynomial" in page.inner_text("#residual-conditions")
    # A curve that stops below the star's charge levels is refused, naming the curve in plain words.
    page.select_option("#residual-kind", "curve")
    page.fill("#residual-curve", "0, 0\n1000, 0.1")
    page.click("#residual-button")
    error = page.wait_for_selector("#residual-error:not([hidden])", timeout=240_000)
    text = error.inner_text()
    assert text.startswith("residual curve:") and "never extrapolated" in text and "residual.curve" not in text
    page.locator("#calibration").screenshot(path=str(ARTIFACTS / "e2e-calibration-residual.png"))


def test_axe_core_finds_no_violations_in_the_calibration_section(page, server):
    axe = pytest.importorskip("axe_playwright_python.sync_playwright")
    page.wait_for_selector("#kernel-result:not([hidden])")
    results = axe.Axe().run(page)
    assert results.violations_count == 0, results.generate_report()
