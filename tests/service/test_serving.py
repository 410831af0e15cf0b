"""The service as it is started for real (issue 26): the README's ``pip install .`` then ``nlpsf serve``
from the clone's root runs its jobs; a job process never imports from the working directory; the
client behind the fair share is the socket's peer unless a trusted proxy is configured."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from ..servers import ROOT, free_port, start_server, wait_for

pytestmark = pytest.mark.slow

SMALL_JOB = {"band": "H158", "magnitudes": [19.0], "betas": [5e-7], "realizations": 3, "fidelity": "linear"}


def _serve(command: list[str], cwd: Path, env: dict[str, str], log: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    process = subprocess.Popen(
        [*command, "serve", "--port", str(port), "--workers", "1"],
        cwd=cwd,
        env=env,
        stdout=open(log, "wb"),  # noqa: SIM115 - the server outlives this call
        stderr=subprocess.STDOUT,
    )
    base = f"http://127.0.0.1:{port}/api/v1"

    def up() -> bool:
        assert process.poll() is None, log.read_text(errors="replace")[-3000:]
        try:
            return httpx.get(f"{base}/health", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_for(up, timeout=180, interval=0.3)
    except BaseException:
        _stop(process)
        raise
    return process, base


def _stop(process: subprocess.Popen) -> None:
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10)


def _job_runs_to_done(base: str, log: Path) -> None:
    submitted = httpx.post(f"{base}/simulations", params={"wait": 120}, json=SMALL_JOB, timeout=180)
    assert submitted.status_code in (200, 202), submitted.text
    ticket = submitted.json()["id"]

    def finished():
        job = httpx.get(f"{base}/simulations/{ticket}", timeout=10).json()
        return job if job["status"] not in ("queued", "running") else None

    final = wait_for(finished, timeout=180, interval=0.5)
    assert final["status"] == "done", (final, log.read_text(errors="replace")[-3000:])
    assert final["result"]["results"][0]["dR_over_R"]["mean"] > 0


def _clean_env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NLPSF_", "PYTHON", "VIRTUAL_ENV"))}
    env.update(HOME=str(home), XDG_STATE_HOME=str(home / "state"))
    return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """``pip install .`` as the README says: the checkout built into a wheel and installed into a
    fresh venv; returns the venv's ``nlpsf`` command."""
    out = tmp_path_factory.mktemp("dist")
    subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(out), str(ROOT)], check=True, capture_output=True, timeout=900
    )
    (wheel,) = out.glob("nlpsf-*.whl")
    venv = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(wheel)], capture_output=True, text=True, timeout=900)
    assert pip.returncode == 0, pip.stderr[-3000:]
    return venv / "bin" / "nlpsf"


def test_the_readme_start_from_the_clones_root_runs_a_job(installed, tmp_path):
    # The clone's root holds the source folder nlpsf/ (without nlpsf/web, which installs from app/):
    # a job process that imported it would fail with "No module named 'nlpsf.web'".
    assert (ROOT / "nlpsf" / "__init__.py").is_file() and not (ROOT / "nlpsf" / "web").exists()
    home = tmp_path / "home"
    home.mkdir()
    log = tmp_path / "server.log"
    server, base = _serve([str(installed)], ROOT, _clean_env(home), log)
    try:
        _job_runs_to_done(base, log)
    finally:
        _stop(server)
    assert "No module named" not in log.read_text(errors="replace")


def test_no_process_of_the_service_imports_from_the_working_directory(tmp_path):
    # The checkout's own command (an editable install: its finder comes after the working
    # directory on the path) in a folder with a package nlpsf/ of its own, which imports but holds
    # nothing (as the clone's source folder holds no nlpsf.web): a process that imported it fails.
    folder = tmp_path / "cwd"
    (folder / "nlpsf").mkdir(parents=True)
    marker = tmp_path / "imported"
    (folder / "nlpsf" / "__init__.py").write_text(f"open({str(marker)!r}, 'a').write('imported\\n')\n")
    home = tmp_path / "home"
    home.mkdir()
    env = {**_clean_env(home), "PATH": os.environ.get("PATH", "")}
    log = tmp_path / "server.log"
    command = Path(sys.executable).parent / "nlpsf"
    server, base = _serve([str(command)], folder, env, log)
    try:
        _job_runs_to_done(base, log)
    finally:
        _stop(server)
    assert not marker.exists(), log.read_text(errors="replace")[-3000:]


# --- whose share: the socket's peer, or a trusted proxy's X-Forwarded-For ------------------------------


LONG = {"band": "H158", "realizations": 3000, "magnitudes": [18.0 + 0.1 * k for k in range(60)], "seed": 11}
QUEUE_ENV = {
    "NLPSF_JOB_WORKERS": "1",
    "NLPSF_MAX_QUEUE": "8",
    "NLPSF_MAX_QUEUE_PER_CLIENT": "1",
    "NLPSF_MAX_REALIZATIONS": "5000",
    "NLPSF_MAX_STAMP_PIXELS": str(10**9),
    "NLPSF_MAX_WORK": str(10**12),
    "NLPSF_WORKERS": "1",
}


def _submissions(base: str) -> list[int]:
    """Statuses of: a long job that runs, then one queued job from "10.0.0.1", then one from
    "10.0.0.2" and another from "10.0.0.1" -- all on this test's one socket address, 127.0.0.1."""
    first = httpx.post(f"{base}/simulations", json=LONG, headers={"X-Forwarded-For": "10.0.0.9"}, timeout=30).json()
    wait_for(lambda: httpx.get(f"{base}/simulations/{first['id']}").json()["status"] == "running", timeout=60)
    statuses = []
    tickets = [first["id"]]
    for seed, client in ((1, "10.0.0.1"), (2, "10.0.0.2"), (3, "10.0.0.1")):
        response = httpx.post(f"{base}/simulations", json={**LONG, "seed": seed}, headers={"X-Forwarded-For": client}, timeout=30)
        statuses.append(response.status_code)
        if response.status_code == 202:
            tickets.append(response.json()["id"])
        else:
            assert response.json()["limit"] == "max_queue_per_client"
    for ticket in tickets:
        httpx.delete(f"{base}/simulations/{ticket}", timeout=30)
    return statuses


def test_x_forwarded_for_is_ignored_unless_the_peer_is_a_trusted_proxy(tmp_path):
    port = free_port()
    server = start_server(tmp_path / "plain.sqlite3", port, env=QUEUE_ENV, log=tmp_path / "plain.log")
    try:
        # One socket address, one client: the header changes nothing, the second job is past its share.
        assert _submissions(f"http://127.0.0.1:{port}/api/v1") == [202, 429, 429]
    finally:
        _stop(server)
    port = free_port()
    trusted = {**QUEUE_ENV, "NLPSF_FORWARDED_ALLOW_IPS": "127.0.0.1"}
    server = start_server(tmp_path / "proxy.sqlite3", port, env=trusted, log=tmp_path / "proxy.log")
    try:
        # Behind a trusted proxy each forwarded client has its own share.
        assert _submissions(f"http://127.0.0.1:{port}/api/v1") == [202, 202, 429]
    finally:
        _stop(server)
