"""Build the Dockerfile and run the image for real (podman through ../shared/tools/container), then
call the running container's health and solve endpoints the way another tool would."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import httpx
import pytest

from nlpsf.slopes import tables
from nlpsf.solve import solver

from ..servers import ROOT, free_port, wait_for

pytestmark = [pytest.mark.container, pytest.mark.slow]


def _container_tool() -> Path | None:
    """The podman wrapper: $NLPSF_CONTAINER_TOOL, else a shared/tools/container beside the checkout or
    any folder above it, else one on PATH. Wherever the clone is, CI finds it (and fails, not skips,
    when it cannot)."""
    if os.environ.get("NLPSF_CONTAINER_TOOL"):
        return Path(os.environ["NLPSF_CONTAINER_TOOL"])
    for folder in [ROOT, *ROOT.parents]:
        candidate = folder / "shared" / "tools" / "container"
        if candidate.is_file():
            return candidate.resolve()
    found = shutil.which("container")
    return Path(found) if found else None


TOOL = _container_tool()
TAG = "localhost/nlpsf:test"
# The same flags the tool gives podman, for the look-ups it does not offer (ps, exec, healthcheck).
PODMAN = ["podman", "--runtime", "runc", "--cgroup-manager=cgroupfs"]


@pytest.fixture(scope="module")
def image():
    if TOOL is None or not TOOL.exists():
        if os.environ.get("CI"):
            pytest.fail("the container test must run in CI, but no shared/tools/container was found (set NLPSF_CONTAINER_TOOL)")
        pytest.skip("no shared/tools/container beside the checkout or above it, nor NLPSF_CONTAINER_TOOL")
    # Docker image format, so that the HEALTHCHECK is kept (podman's default OCI format drops it).
    env = {**os.environ, "BUILDAH_FORMAT": "docker"}
    build = subprocess.run([str(TOOL), "build", TAG], cwd=ROOT, env=env, capture_output=True, text=True, timeout=3000)
    assert build.returncode == 0, build.stdout[-4000:] + build.stderr[-4000:]
    return TAG


@pytest.fixture(scope="module")
def container(image):
    port = free_port()
    # The image's own command, with the port and the worker count set through the environment.
    command = ["env", f"PORT={port}", "NLPSF_WORKERS=2", "sh", "-c", 'exec nlpsf serve --host 0.0.0.0 --port "$PORT"']
    process = subprocess.Popen([str(TOOL), "run", image, *command], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"

    def up():
        assert process.poll() is None, process.stdout.read().decode(errors="replace")[-4000:]
        try:
            return httpx.get(f"{base}/api/v1/health", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    ids: list[str] = []
    try:
        wait_for(up, timeout=180, interval=0.5)
        listing = subprocess.run([*PODMAN, "ps", "-q", "--filter", f"ancestor={image}"], capture_output=True, text=True)
        ids = listing.stdout.split()
        assert len(ids) == 1, ids
        yield base, ids[0]
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            subprocess.run([*PODMAN, "stop", "-t", "5", *ids], capture_output=True)
            process.kill()


def test_health_and_solve_in_the_container(container):
    base, _ = container
    assert httpx.get(f"{base}/api/v1/health").json()["status"] == "ok"
    body = {"band": "H158", "sca": 18, "metric": "size", "mode": "bias", "beta0": 5e-7, "exptime": 168.1, "magnitude": 18.3}
    response = httpx.post(f"{base}/api/v1/solve", json={**body, "tolerance": 1e-4}, timeout=30)
    assert response.status_code == 200, response.text
    served = response.json()
    local = solver.solve(**body, tolerance=1e-4).to_dict()
    assert served["solved_for"] == "precision"
    assert served["precision"] == pytest.approx(local["precision"], rel=1e-12)
    assert served["uncertainty"] == pytest.approx(local["uncertainty"], rel=1e-12)
    bad = httpx.post(f"{base}/api/v1/solve", json={**body, "tolerance": -1})
    assert bad.status_code == 422 and bad.json()["field"] == "tolerance"


def test_the_image_serves_the_shipped_tables_and_the_page(container):
    base, _ = container
    meta = httpx.get(f"{base}/api/v1/meta").json()
    assert meta["tables"]["fingerprint"] == tables.load_tables().meta["fingerprint"]
    page = httpx.get(f"{base}/")
    assert page.status_code == 200 and "uPlot" in page.text
    assert httpx.get(f"{base}/vendor/uPlot.iife.min.js").status_code == 200


def test_small_simulation_in_the_container(container):
    base, _ = container
    job = httpx.post(
        f"{base}/api/v1/simulations", params={"wait": 120}, json={"magnitudes": [19.0], "realizations": 8}, timeout=130
    ).json()
    assert job["status"] == "done", job
    assert job["result"]["results"][0]["dR_over_R"]["mean"] > 0


def test_non_root_health_check_and_worker_count(container):
    base, container_id = container
    user = subprocess.run([*PODMAN, "exec", container_id, "id", "-u"], capture_output=True, text=True)
    assert user.stdout.strip() == "10001"
    # The image's HEALTHCHECK, run as podman would run it, with the port this container listens on.
    inspect = subprocess.run([*PODMAN, "image", "inspect", TAG, "--format", "{{json .Config.Healthcheck}}"], capture_output=True)
    check = json.loads(inspect.stdout)["Test"]
    assert check[0] == "CMD-SHELL" and "/api/v1/health" in check[1]
    port = base.rsplit(":", 1)[1]
    health = subprocess.run([*PODMAN, "exec", "-e", f"PORT={port}", container_id, "sh", "-c", check[1]], capture_output=True)
    assert health.returncode == 0, health.stdout + health.stderr
    wrong = subprocess.run([*PODMAN, "exec", "-e", "PORT=1", container_id, "sh", "-c", check[1]], capture_output=True)
    assert wrong.returncode != 0, "the health check must fail when nothing answers"
    count = (
        "import os; print(sum('spawn_main' in open(f'/proc/{p}/cmdline').read()"
        " for p in os.listdir('/proc') if p.isdigit() and int(p) != os.getpid()))"
    )
    workers = subprocess.run([*PODMAN, "exec", container_id, "python", "-c", count], capture_output=True, text=True)
    assert workers.stdout.strip() == "2", workers.stdout + workers.stderr
