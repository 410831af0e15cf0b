"""The page follows a solve that became a job (202): with the service answering simulating solves at
once with a job (NLPSF_SOLVE_WAIT_S=0), a linear-fidelity solve still ends in an answer on the page."""

from __future__ import annotations

import signal

import pytest

from ..servers import free_port, start_server

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    directory = tmp_path_factory.mktemp("e2e-jobs")
    port = free_port()
    process = start_server(directory / "jobs.sqlite3", port, env={"NLPSF_SOLVE_WAIT_S": "0"}, log=directory / "server.log")
    yield f"http://127.0.0.1:{port}/"
    process.send_signal(signal.SIGTERM)
    process.wait(20)


def test_a_solve_answered_with_a_job_is_followed_to_its_answer(page):
    page.check("#solve-for-precision")
    page.fill("#solve-tolerance", "1e-4")
    page.fill("#solve-magnitude", "19")
    page.select_option("#solve-fidelity", "linear")
    with page.expect_response(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as response:
        page.click("#solve-button")
    assert response.value.status == 202
    page.wait_for_selector("[data-testid=solve-answer]", timeout=120_000)
    assert "linear" in page.inner_text("#calculator")
