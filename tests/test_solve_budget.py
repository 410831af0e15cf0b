"""The solver with a shear budget in place of the tolerance, and scatter averaged over stars."""

import functools
import json
import math

import pytest

from nlpsf import cli, shear, solver
from nlpsf.checks import InputError

# These tests check the paper's tables and relations: the paper's scene (the default is the Roman star's).
paper_solve = functools.partial(solver.solve, scene="paper")


@pytest.mark.parametrize(("metric", "kind"), [("size", "m"), ("e1", "c"), ("e2", "c"), ("e", "c")])
def test_a_shear_budget_gives_the_same_answer_as_the_tolerance_it_implies(metric, kind):
    ratio = [(1.2, 0.3), (1.5, 0.5), (2.0, 0.2)]
    budget = {f"shear_{kind}": 1e-3 if kind == "m" else 2e-4}
    by_budget = paper_solve("H158", metric=metric, magnitude=19.0, size_ratio=ratio, **budget)
    effective = shear.check_size_ratio(ratio).effective
    tolerance = 1e-3 * effective**2 / 2 if kind == "m" else 2 * 2e-4 * effective**2
    by_tolerance = paper_solve("H158", metric=metric, magnitude=19.0, tolerance=tolerance)
    assert by_budget.tolerance == pytest.approx(tolerance, rel=1e-14)
    assert by_budget.precision == pytest.approx(by_tolerance.precision, rel=1e-12)
    answer = by_budget.to_dict()
    assert answer["tolerance"] == pytest.approx(tolerance, rel=1e-14)
    assert answer["shear"][kind] == budget[f"shear_{kind}"]
    assert answer["shear"]["tolerance"] == answer["tolerance"]
    assert answer["shear"]["size_ratio"]["ratios"] == [1.2, 1.5, 2.0]
    assert answer["shear"]["given"] == kind


def test_a_size_ratio_alone_reports_the_implied_bias_and_it_round_trips():
    first = paper_solve("J129", metric="size", precision=0.02, magnitude=19.5, size_ratio=1.4)
    implied = first.shear
    assert implied["given"] == "tolerance"
    assert implied["m"] == pytest.approx(shear.multiplicative_bias(first.tolerance, shear.check_size_ratio(1.4)))
    assert implied["uncertainty"] == pytest.approx(first.uncertainty_statistical * 2 / 1.4**2)
    back = paper_solve("J129", metric="size", magnitude=19.5, shear_m=implied["m"], size_ratio=1.4)
    assert back.precision == pytest.approx(0.02, rel=1e-12)
    # And the magnitude from (precision, budget) is the one we started from.
    mag = paper_solve("J129", metric="size", precision=0.02, shear_m=implied["m"], size_ratio=1.4)
    assert mag.magnitude == pytest.approx(19.5, abs=1e-3)


@pytest.mark.parametrize("metric", ["size", "e1", "e"])
def test_scatter_averaged_over_n_stars_falls_as_one_over_sqrt_n(metric):
    one = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, magnitude=19.0)
    many = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, magnitude=19.0, stars=25)
    assert many.tolerance == pytest.approx(one.tolerance / 5, rel=1e-12)
    assert many.slope == one.slope  # the slope is still one star's
    assert "25 stars" in many.applies_to and many.conditions["stars"] == 25
    assert "sqrt(stars)" in many.conditions["relation"]
    assert one.applies_to.startswith("one star")
    # Solving for the magnitude: n stars at tolerance T are one star at tolerance T sqrt(n).
    m_many = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, tolerance=1e-5, stars=25)
    m_one = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, tolerance=5e-5)
    assert m_many.nonlinearity_magnitude == pytest.approx(m_one.nonlinearity_magnitude, abs=1e-6)
    precision = paper_solve("H158", metric=metric, mode="scatter", tolerance=1e-5, magnitude=19.0, stars=25)
    assert precision.precision == pytest.approx(
        5 * paper_solve("H158", metric=metric, mode="scatter", tolerance=1e-5, magnitude=19.0).precision
    )


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mode": "bias", "stars": 4, "tolerance": 1e-4}, "stars"),
        ({"mode": "scatter", "stars": 0, "tolerance": 1e-4}, "stars"),
        ({"mode": "scatter", "stars": 1.5, "tolerance": 1e-4}, "stars"),
        ({"shear_m": 1e-3, "size_ratio": 1.5, "tolerance": 1e-4}, "tolerance"),
        ({"shear_m": 1e-3}, "size_ratio"),
        ({"shear_c": 1e-3, "size_ratio": 1.5}, "shear_c"),
        ({"metric": "e1", "shear_m": 1e-3, "size_ratio": 1.5}, "shear_m"),
        ({"shear_m": 1e-3, "size_ratio": 1.5, "precision": 0.01}, "shear_m"),
        ({"shear_m": 1e-3, "size_ratio": -1}, "size_ratio"),
        ({"shear_m": 1e-13, "size_ratio": 1e-3}, "shear_m"),
        ({"size_ratio": "1:x", "tolerance": 1e-4}, "size_ratio"),
    ],
)
def test_bad_budget_requests_name_the_field(kwargs, field):
    kwargs = {"magnitude": 19.0, **kwargs}
    with pytest.raises(InputError) as info:
        paper_solve("H158", **kwargs)
    assert info.value.argument == field


def test_cli_shear_json_contract(capsys):
    code = cli.main(
        ["solve", "--metric", "e2", "--shear-c", "1e-4", "--size-ratio", "1.5", "--magnitude", "19", "--json", "--scene", "paper"]
    )
    assert code == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["shear"]["c"] == 1e-4 and payload["shear"]["size_ratio"] == 1.5
    assert payload["tolerance"] == pytest.approx(2 * 1e-4 * 1.5**2) == payload["shear"]["tolerance"]
    assert payload["solved_for"] == "precision" and math.isfinite(payload["precision"])
    assert cli.main(["solve", "--shear-m", "1e-3", "--magnitude", "19"]) == 2
    assert "--size-ratio" in capsys.readouterr().err
    assert (
        cli.main(["solve", "--mode", "scatter", "--stars", "9", "--precision", "0.1", "--magnitude", "19", "--scene", "paper"])
        == 0
    )
    assert "9 stars" in capsys.readouterr().out


def test_web_request_takes_the_new_fields_and_refuses_a_file():
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app

    client = TestClient(create_app())
    body = {"band": "H158", "magnitude": 19.0, "shear_m": 1e-3, "size_ratio": [[1.2, 1.0], [2.0, 1.0]], "scene": "paper"}
    answer = client.post("/api/v1/solve", json=body)
    assert answer.status_code == 200, answer.text
    assert answer.json()["shear"]["m"] == 1e-3
    scatter = client.post(
        "/api/v1/solve",
        json={"band": "H158", "mode": "scatter", "magnitude": 19.0, "tolerance": 1e-4, "stars": 4, "scene": "paper"},
    )
    assert scatter.status_code == 200 and scatter.json()["stars"] == 4
    refused = client.post("/api/v1/solve", json={**body, "size_ratio": "@/etc/passwd"})
    assert refused.status_code == 422
