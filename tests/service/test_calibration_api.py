"""The calibration endpoints (app/calibration_api.py, docs/calibration.md): real simulations in job processes.

Checked against independent facts: the kernel's quadratic residual is the slope POST /solve reports for the
same star (the beta path); a quadratic residual given as a polynomial, a shape or a curve is Delta_beta times
that slope; two calibrations' per-pixel polynomials sent inline give what ``nlpsf residual`` gives from two
linearity files made by roman_datamodels; the ECSV download is ``nlpsf kernel --output``'s. Refusals name the
field, within the service's body limit; kernels are jobs (queued, cancellable, stored).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from nlpsf.web.settings import Limits

from ..servers import finished_job, wait_for

STAR = {"band": "H158", "sca": 7, "magnitude": 19.0, "scene": {"position": [900.0, 3100.0]}}
rng = np.random.default_rng(2929)


@pytest.fixture(scope="module")
def client_settings() -> dict:
    return {"limits": Limits(max_realizations=500, max_stamp=128, max_grid=50), "max_queue": 8, "max_queue_per_client": 8}


def answer(client, path: str, body: dict) -> tuple[int, dict, str | None]:
    """(status, body, job id) of a POST whose answer may be a job: a 202 is followed to its end (a failed job's
    input error is the 422 the submitter would have had, as ``job_answer`` gives it)."""
    response = client.post(path, json=body)
    location = response.headers.get("location")
    job_id = location.rsplit("/", 1)[1] if location else None
    if response.status_code != 202:
        return response.status_code, response.json(), job_id
    job = finished_job(client, response.json()["id"]).json()
    if job["status"] == "done":
        return 200, job["result"], job_id
    error = job.get("error") or {}
    return (422 if error.get("field") else 500), {"field": error.get("field"), "detail": job.get("message")}, job_id


def solve_slope(client, metric: str) -> float:
    status, solution, _ = answer(client, "/api/v1/solve", {**STAR, "metric": metric, "precision": 0.01, "fidelity": "linear"})
    assert status == 200, solution
    assert solution["conditions"]["residual_nl"] == "per_resultant_correction"
    return solution["slope"]


@pytest.fixture(scope="module")
def kernel_answer(client):
    status, kernel, job_id = answer(client, "/api/v1/calibration/kernel", STAR)
    assert status == 200, kernel
    return kernel, job_id


@pytest.fixture(scope="module")
def slopes(client):
    return {metric: solve_slope(client, metric) for metric in ("size", "e1", "e2", "e")}


def test_the_kernels_quadratic_residual_is_the_slope_post_solve_reports(kernel_answer, slopes):
    kernel, _ = kernel_answer
    columns, meta = kernel["columns"], kernel["meta"]
    q = np.array(columns["charge_e"])
    for metric, slope in slopes.items():
        assert meta["quadratic_slopes"][metric]["value"] == pytest.approx(slope, rel=0.01), metric
        integral = float(np.trapezoid(np.array(columns[metric]) * -(q**2), q))
        assert integral == pytest.approx(slope, rel=0.01), metric
    assert meta["units"]["charge_e"] == "electron" and meta["units"]["size"] == "1 / electron"
    low, high = meta["signal_range_e"]["size"]
    assert 0 < low < high <= meta["saturation_e"]
    assert meta["conditions"]["residual_nl"] == "per_resultant_correction"
    assert meta["conditions"]["scene"]["position"] == [900.0, 3100.0]


def test_the_ecsv_download_is_the_clis(client, kernel_answer, tmp_path, monkeypatch):
    from astropy.table import Table

    from nlpsf.cli import main

    _, job_id = kernel_answer
    download = client.get(f"/api/v1/calibration/kernel/{job_id}.ecsv")
    assert download.status_code == 200
    assert download.headers["content-type"].startswith("text/x-ecsv")
    assert "nlpsf-kernel-H158-sca7" in download.headers["content-disposition"]
    ours = Table.read(download.text, format="ascii.ecsv")
    monkeypatch.chdir(tmp_path)
    assert (
        main(["kernel", "--band", "H158", "--sca", "7", "--magnitude", "19", "--position", "900,3100", "--output", "k.ecsv"]) == 0
    )
    cli = Table.read(tmp_path / "k.ecsv", format="ascii.ecsv")
    assert ours.colnames == cli.colnames
    for name in cli.colnames:
        assert ours[name].unit == cli[name].unit, name
        assert np.allclose(ours[name], cli[name], rtol=1e-12, atol=0, equal_nan=True), name
    # Anything but a finished kernel job is not a kernel.
    assert client.get(f"/api/v1/calibration/kernel/{'0' * 32}.ecsv").status_code == 404
    _, _, solve_id = answer(client, "/api/v1/solve", {**STAR, "precision": 0.01, "fidelity": "linear"})
    assert client.get(f"/api/v1/calibration/kernel/{solve_id}.ecsv").status_code == 404


def test_a_quadratic_residual_in_any_form_is_delta_beta_times_the_slope(client, slopes, kernel_answer):
    delta = float(rng.uniform(1e-9, 2e-8))
    forms = {
        "polynomial": {"polynomial": [0.0, 0.0, -delta]},
        "shape": {"shape": "quadratic", "scale": delta},
    }
    top = kernel_answer[0]["columns"]["charge_e"][-1]
    q = np.linspace(0.0, top, 1000)
    forms["curve"] = {"curve": {"charge_e": q.tolist(), "residual_e": (-delta * q**2).tolist()}}
    for name, residual in forms.items():
        status, effect, _ = answer(client, "/api/v1/calibration/residual", {**STAR, "residual": residual})
        assert status == 200, (name, effect)
        for metric in ("size", "e1", "e2", "e"):
            value = effect["bias"][metric]["value"]
            # the curve is linear between 1000 points: within (dQ)^2 / 4 of -delta Q^2
            assert value == pytest.approx(delta * slopes[metric], rel=2e-3 if name == "curve" else 1e-4), (name, metric)
            assert effect["bias"][metric]["uncertainty"] >= 0
        assert effect["conditions"]["band"] == "H158" and effect["flag_codes"] == []
        assert effect["units"]["size"].startswith("dimensionless")


def test_the_requirement_for_a_quadratic_shape_is_the_beta_answer_and_a_gain_error_is_refused(client, slopes):
    tolerance = 1e-4
    status, answer_, _ = answer(client, "/api/v1/calibration/requirement", {**STAR, "shape": "quadratic", "tolerance": tolerance})
    assert status == 200, answer_
    assert answer_["solved_for"] == "scale"
    # r = -s Q^2 is Delta_beta = s: the tolerance over the solver's slope
    assert answer_["scale"] == pytest.approx(tolerance / abs(slopes["size"]), rel=1e-4)
    status, problem, _ = answer(
        client, "/api/v1/calibration/requirement", {**STAR, "shape": "constant_fraction", "tolerance": tolerance}
    )
    assert status == 422 and problem["field"] == "shape" and "gain error" in problem["detail"]


def _linearity_file(path, coeffs):
    from roman_datamodels import datamodels as rdd

    model = rdd.LinearityRefModel.create_fake_data(shape=coeffs.shape)
    model.coeffs = coeffs.astype(np.float32)
    model.dq = np.zeros(coeffs.shape[1:], dtype=np.uint32)
    model.save(str(path))
    return path


def _inverse_dn(beta_e: float, gain: float, order: int, shape) -> np.ndarray:
    import math

    c = np.zeros((order + 1, *shape))
    for k in range(order):
        c[k + 1] = math.comb(2 * k, k) / (k + 1) * beta_e**k * gain**k
    return c


def test_two_calibrations_inline_are_what_nlpsf_residual_reads_from_their_files(client, tmp_path, capsys):
    pytest.importorskip("roman_datamodels")
    from nlpsf.cli import main

    corner = {"band": "H158", "sca": 7, "magnitude": 18.5, "scene": {"position": [30.0, 28.0]}}
    gain = 1.8
    reference = _inverse_dn(5e-7, gain, 5, (48, 48))
    applied = reference.copy()
    row, col = 28 + int(rng.integers(-2, 3)), 30 + int(rng.integers(-2, 3))  # near the star (science pixels)
    k = int(rng.integers(1, 4))
    applied[k, row - 1, col - 1] *= 1 + rng.choice([-1, 1]) * rng.uniform(0.01, 0.03)
    applied[4] *= 0.9  # and every pixel's quartic term
    files = [_linearity_file(tmp_path / f"{name}.asdf", c) for name, c in (("applied", applied), ("reference", reference))]
    argv = ["residual", "--band", "H158", "--sca", "7", "--magnitude", "18.5", "--position", "30,28", "--gain", str(gain)]
    assert main([*argv, "--linearity", str(files[0]), "--reference", str(files[1]), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    r0, r1 = cli["conditions"]["measured_pixels"]["rows"]
    c0, c1 = cli["conditions"]["measured_pixels"]["columns"]
    assert (r1 - r0, c1 - c0) == (8, 8)
    # inline: the measured pixels and one ring of star-free pixels around them (float32, as the files hold them)
    block = (slice(None), slice(r0 - 2, r1 + 1), slice(c0 - 2, c1 + 1))
    linearity = {
        "applied": applied.astype(np.float32)[block].astype(float).tolist(),
        "reference": reference.astype(np.float32)[block].astype(float).tolist(),
        "first_row": r0 - 1,
        "first_column": c0 - 1,
        "gain": gain,
    }
    body = {**corner, "residual": {"linearity": linearity}}
    assert len(json.dumps(body)) < 65_536  # within the default body limit
    status, effect, _ = answer(client, "/api/v1/calibration/residual", body)
    assert status == 200, effect
    assert effect["conditions"]["sky_pixels"] == 11 * 11 - 9 * 9
    for part in ("bias", "total", "scatter"):
        for metric, value in cli[part].items():
            assert effect[part][metric]["value"] == pytest.approx(value["value"], rel=1e-9, abs=1e-15), (part, metric)
    assert abs(effect["total"]["size"]["value"]) > 0 and effect["scatter"]["size"]["value"] > 0


def _body(residual: dict, **star) -> dict:
    return {**STAR, **star, "residual": residual}


def test_refusals_name_the_field(client):
    square = _inverse_dn(5e-7, 2.0, 3, (3, 3)).tolist()
    wide = _inverse_dn(5e-7, 2.0, 3, (13, 13))
    falling = wide.copy()
    falling[2] = -1e-3  # dF_c / dF = 1 - 2e-3 F: falls past 500 DN
    cases = [
        (_body({"polynomial": [0.0, 1e-3], "shape": "quadratic", "scale": 1e-9}), "residual"),
        (_body({}), "residual"),
        (_body({"shape": "quadratic"}), "residual.scale"),
        (_body({"polynomial": [0.0, 1e-3], "scale": 2.0}), "residual.scale"),
        (_body({"shape": "power_law:99", "scale": 1.0}), "residual.shape"),
        (_body({"shape": "cubic", "scale": 1.0}), "residual.shape"),
        (_body({"polynomial": [0.0, "1e-3"]}), "residual.polynomial"),
        (_body({"curve": {"charge_e": [0.0, 2.0, 1.0], "residual_e": [0.0, 1.0, 2.0]}}), "residual.curve"),
        (_body({"curve": {"charge_e": [0.0, 10.0], "residual_e": [0.0, 1.0]}}), "residual.curve"),  # the star goes higher
        (_body({"linearity": {"applied": [[[1.0, 2.0], [3.0]]], "reference": square, "first_row": 3099, "first_column": 899}}),
         "residual.linearity.applied"),
        (_body({"linearity": {"applied": square, "reference": square, "first_row": 3099, "first_column": 899}}),
         "residual.linearity"),  # 3 x 3 pixels: not the 9 x 9 the measurement reads
        (_body({"linearity": {"applied": falling.tolist(), "reference": wide.tolist(), "first_row": 3094, "first_column": 894}}),
         "residual.linearity"),
        (_body({"linearity": {"applied": square, "reference": square, "first_row": 4087, "first_column": 1}}),
         "residual.linearity.applied"),  # off the SCA
        (_body({"polynomial": [0.0]}, precision=0.01), "precision"),
        (_body({"polynomial": [0.0]}, sca=19), "sca"),
    ]  # fmt: skip
    for body, field in cases:
        status, problem, _ = answer(client, "/api/v1/calibration/residual", body)
        assert status == 422 and problem["field"] == field, (field, problem)
    # The scene's field is named as POST /solve names it (the preset's name or the object: both tried).
    response = client.post("/api/v1/calibration/residual", json=_body({"polynomial": [0.0]}, scene={"jitter": 5.0}))
    assert response.status_code == 422 and "scene.jitter" in response.json()["detail"]
    kernel = {k: v for k, v in STAR.items() if k != "magnitude"}
    response = client.post("/api/v1/calibration/kernel", json=kernel)
    assert response.status_code == 422 and response.json()["field"] == "magnitude"
    # A star too bright for its readout is the request's fault, named, not a server error.
    status, problem, _ = answer(client, "/api/v1/calibration/kernel", {**STAR, "magnitude": 5.0})
    assert status == 422 and problem["field"] == "magnitude" and "too bright" in problem["detail"]
    requirement = {**STAR, "shape": "power_law:2", "tolerance": 1e-4, "scale": 1.0}
    response = client.post("/api/v1/calibration/requirement", json=requirement)
    assert response.status_code == 422 and response.json()["field"] == "scale"
    response = client.post("/api/v1/calibration/requirement", json={**STAR, "shape": "quadratic", "envelope": [18.0, 20.0]})
    assert response.status_code == 422 and response.json()["field"] == "tolerance"
    # A curve of 10,000 points is over the 64 kB body limit: refused before it is read.
    q = np.linspace(0.0, 2e5, 10_000)
    response = client.post(
        "/api/v1/calibration/residual", json=_body({"curve": {"charge_e": q.tolist(), "residual_e": q.tolist()}})
    )
    assert response.status_code == 413


def test_a_calibration_job_is_queued_stored_and_cancellable(make_client):
    long_simulation = {"band": "H158", "realizations": 3000, "magnitudes": [18.0 + 0.1 * k for k in range(60)], "seed": 11}
    settings = {"solve_wait_s": 0.0, "limits": Limits(max_realizations=5000, max_stamp_pixels=10**9, max_work=10**12)}
    with make_client(**settings) as client:
        first = client.post("/api/v1/simulations", json=long_simulation).json()
        queued = client.post("/api/v1/calibration/kernel", json=STAR)
        assert queued.status_code == 202 and queued.json()["status"] == "queued"
        assert queued.json()["request"]["kind"] == "kernel"
        cancelled = client.delete(f"/api/v1/simulations/{queued.json()['id']}").json()
        assert cancelled["status"] == "cancelled" and cancelled["started_at"] is None
        client.delete(f"/api/v1/simulations/{first['id']}")
        # A magnitude scan for an envelope is cancelled while it runs.
        scan = {**{k: v for k, v in STAR.items() if k != "magnitude"}, "shape": "quadratic", "tolerance": 1e-4}
        running = client.post("/api/v1/calibration/requirement", json={**scan, "envelope": [18.0, 26.0]}).json()
        wait_for(lambda: client.get(f"/api/v1/simulations/{running['id']}").json()["status"] == "running")
        assert client.delete(f"/api/v1/simulations/{running['id']}").json()["status"] == "cancelled"
        # A kernel runs to the end with its progress, and the same request is answered from the stored result.
        job = finished_job(client, client.post("/api/v1/calibration/kernel", json=STAR).json()["id"]).json()
        assert job["status"] == "done" and job["progress"] == 1.0 and job["message"] == "done"
        again = client.post("/api/v1/calibration/kernel", json=STAR)
        assert again.status_code == 200 and again.json()["meta"] == job["result"]["meta"]


def test_the_api_docs_example_is_what_the_service_answers(client):
    """docs/api.md's calibration example: the request as shown, and each number shown in the response."""
    text = (Path(__file__).parents[2] / "docs" / "api.md").read_text()
    section = text.split("## Calibration", 1)[1].split("\n## ", 1)[0]
    request_block, response_block = re.findall(r"```json\n(.*?)```", section, re.S)[:2]
    request = json.loads(request_block)
    shown = json.loads(response_block)
    status, effect, _ = answer(client, "/api/v1/calibration/residual", request)
    assert status == 200, effect
    for part, metrics in shown.items():
        if not isinstance(metrics, dict):
            assert effect[part] == metrics, part
            continue
        for metric, value in metrics.items():
            for key, number in value.items():
                assert effect[part][metric][key] == pytest.approx(number, rel=5e-4), (part, metric, key)
