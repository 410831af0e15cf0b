"""What the browser tests share: where Chromium is and how it starts, where screenshots go, and the
page actions several tests take."""

from __future__ import annotations

import os
import shutil

from ..servers import ROOT

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARTIFACTS = ROOT / "test-artifacts"  # screenshots and downloads of the browser tests
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def browser_missing() -> str | None:
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "the playwright package is not installed (pip install playwright; never `playwright install`)"
    if not os.path.exists(CHROMIUM):
        return "Debian's chromium is not installed (apt-get install -y chromium)"
    return None


def answer_point_is_drawn(page) -> bool:
    """True when the canvas pixel at the answer's (magnitude, |slope|) is the marker's red."""
    return page.evaluate(
        """() => {
            const u = state.plots.calc;
            const series = state.exports.calc.columns.findIndex((c) => c.answer) + 1;
            const marker = u.data[series].findIndex((v) => v != null);
            const x = u.valToPos(u.data[0][marker], "x", true);
            const y = u.valToPos(u.data[series][marker], "y", true);
            const [r, g, b] = u.ctx.getImageData(Math.round(x), Math.round(y), 1, 1).data;
            return r > 150 && g < 80 && b < 80;
        }"""
    )


def solve_for(page, unknown: str, given: dict[str, str]) -> str:
    page.check(f"#solve-for-{unknown}")
    for name, value in given.items():
        page.fill(f"#solve-{name}", value)
    # A solve still in flight (a default answer can be a job) finishes first: its answer is not this one.
    page.wait_for_function("() => !document.getElementById('solve-button').disabled", timeout=240_000)
    # The plots of this answer, not the previous one's: their point marks are set when they are drawn.
    page.evaluate(
        """() => {
            state.lastSolution = undefined;
            for (const p of ['req', 'calc']) delete document.getElementById(`plot-${p}`).dataset.point;
        }"""
    )
    with page.expect_response(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as response:
        page.click("#solve-button")
    # 200: answered at once; 202: simulated as a job (the Roman default's answers off the tables),
    # which the page follows to its answer.
    assert response.value.status in (200, 202), response.value.text()
    page.wait_for_function("() => state.lastSolution !== undefined", timeout=240_000)
    page.wait_for_function("() => document.getElementById('plot-calc').dataset.point !== undefined")
    page.wait_for_selector("[data-testid=solve-answer]")
    return response.value.json() if response.value.status == 200 else page.evaluate("() => state.lastSolution")
