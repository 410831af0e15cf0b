"""The server stops under the page and starts again (same port, same job store): the page names the
unreachable server, retries, follows the same job again and shows how the server's record says it
ended, for a solve that became a job and for a fresh simulation."""

from __future__ import annotations

import signal

import httpx
import pytest

from ..servers import free_port, start_server, wait_for
from .browser import ARTIFACTS

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

FINISHED = ("done", "failed", "cancelled", "interrupted")


class Restartable:
    def __init__(self, directory):
        self.directory = directory
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}/"
        self.process = None
        self.starts = 0

    def start(self):
        self.starts += 1
        self.process = start_server(
            self.directory / "jobs.sqlite3",
            self.port,
            env={"NLPSF_SOLVE_WAIT_S": "0"},
            log=self.directory / f"server-{self.starts}.log",
        )

    def kill(self):
        # As a crash or a pulled plug: no graceful shutdown, the job's row still says running.
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(20)

    def stop(self):
        if self.process and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            self.process.wait(20)


@pytest.fixture(scope="module")
def restartable(tmp_path_factory):
    server = Restartable(tmp_path_factory.mktemp("e2e-restart"))
    server.start()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def server(restartable):
    return restartable.url


DOWN = "() => document.getElementById('connection').textContent.includes('cannot be reached')"
ENDED = (
    "() => ['done', 'failed', 'cancelled', 'interrupted'].includes(document.getElementById('sim-progress-text').dataset.status)"
)


def banner(tab) -> str:
    return tab.inner_text("#connection") if tab.is_visible("#connection") else ""


def job_record(restartable, job_id: str) -> dict:
    return httpx.get(f"{restartable.url}api/v1/simulations/{job_id}", timeout=10).json()


def test_server_stopped_mid_simulation_and_started_again(page, restartable):
    page.fill("#sim-magnitudes", "18, 18.5, 19, 19.5, 20")
    page.fill("#sim-betas", "2.5e-7, 5e-7, 1e-6")
    page.fill("#sim-realizations", "150")
    page.fill("#sim-seed", "23")
    with page.expect_response(lambda r: r.url.endswith("/api/v1/simulations") and r.request.method == "POST") as response:
        page.click("#sim-button")
    job_id = response.value.json()["id"]
    page.wait_for_function("() => document.getElementById('sim-progress-text').dataset.status === 'running'", timeout=60_000)
    restartable.kill()
    page.wait_for_function(
        "() => document.getElementById('connection').textContent.includes('cannot be reached')", timeout=30_000
    )
    text = banner(page)
    assert restartable.url in text and "Retrying" in text
    assert "cannot be reached" in page.inner_text("[data-testid=sim-progress-text]")
    page.screenshot(path=str(ARTIFACTS / "e2e-server-down.png"))
    restartable.start()
    page.wait_for_function(ENDED, timeout=300_000)
    shown = page.get_attribute("[data-testid=sim-progress-text]", "data-status")
    print(f"after the restart the simulation ended {shown}")
    record = wait_for(lambda: (r := job_record(restartable, job_id))["status"] in FINISHED and r, timeout=60)
    assert shown == record["status"], f"the page shows {shown}, the server's record says {record['status']}"
    if shown == "done":
        page.wait_for_function("() => document.querySelectorAll('#sim-table tbody tr').length === 15", timeout=30_000)
    else:
        assert record["status"] in page.inner_text("#sim-error")
    assert not page.evaluate("() => sessionStorage.getItem('nlpsf-job')")


def test_server_stopped_mid_solve_and_started_again(page, restartable):
    page.check("#solve-for-precision")
    page.fill("#solve-tolerance", "1e-4")
    page.fill("#solve-magnitude", "19.25")
    page.select_option("#solve-fidelity", "linear")
    with page.expect_response(lambda r: r.url.split("?")[0].endswith("/api/v1/solve")) as response:
        page.click("#solve-button")
    assert response.value.status == 202
    job_id = response.value.json()["id"]
    restartable.kill()
    page.wait_for_function(
        "() => document.getElementById('connection').textContent.includes('cannot be reached')", timeout=30_000
    )
    assert page.inner_text("#solve-button") in ("Simulating…", "Solving…")
    assert "stale" in page.get_attribute("#solve-result", "class"), "the previous answer is greyed while the new one is pending"
    restartable.start()
    page.wait_for_function(
        "() => document.querySelector('#solve-result:not(.stale) [data-testid=solve-answer]')"
        " || !document.getElementById('solve-error').hidden",
        timeout=300_000,
    )
    record = wait_for(lambda: (r := job_record(restartable, job_id))["status"] in FINISHED and r, timeout=60)
    print(f"after the restart the solve's job ended {record['status']}")
    if record["status"] == "done":
        headline = page.inner_text("[data-testid=solve-answer]")
        precision = record["result"]["precision"]
        assert f"{100 * precision:.2f}"[:3] in headline, (headline, precision)
        assert "linear" in page.inner_text("#solve-result")
    else:
        assert record["status"].rstrip("ed") in page.inner_text("#solve-error")
        assert page.input_value("#solve-precision") == ""
    wait_for(lambda: not banner(page).startswith("The nlpsf server"), timeout=30)
    page.select_option("#solve-fidelity", "table")


def test_a_reload_follows_the_same_simulation(page, restartable):
    page.fill("#sim-magnitudes", "18, 18.5, 19, 19.5")
    page.fill("#sim-betas", "2.5e-7, 5e-7, 1e-6")
    page.fill("#sim-realizations", "150")
    page.fill("#sim-seed", "29")
    with page.expect_response(lambda r: r.url.endswith("/api/v1/simulations") and r.request.method == "POST") as response:
        page.click("#sim-button")
    job_id = response.value.json()["id"]
    page.wait_for_function("() => document.getElementById('sim-progress-text').dataset.status === 'running'", timeout=60_000)
    page.reload()
    page.wait_for_selector("body[data-ready='true']")
    page.wait_for_function(ENDED, timeout=300_000)
    record = job_record(restartable, job_id)
    assert page.get_attribute("[data-testid=sim-progress-text]", "data-status") == record["status"] == "done"
    page.wait_for_function("() => document.querySelectorAll('#sim-table tbody tr').length === 12", timeout=30_000)
