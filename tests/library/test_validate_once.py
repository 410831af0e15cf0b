"""A request is validated where it comes in, once; what it flows through trusts it (issue 25: one
W146 solve without a position used to check its band 1,157 times)."""

import pytest

from nlpsf import SolveRequest, answer, roman


@pytest.mark.parametrize(
    "body",
    [
        {"band": "W146", "sca": 7, "magnitude": 20.0, "tolerance": 1e-3},  # the SCA's 25 nodes
        {"band": "H158", "sca": 3, "precision": 0.01, "tolerance": 1e-3, "metric": "e"},  # a magnitude solve
        {"band": "Y106", "sca": 4, "magnitude": 19.0, "precision": 0.01, "scene": "paper"},
        # at a position: the scene object over the default's sky
        {"band": "J129", "sca": 5, "magnitude": 19.0, "tolerance": 1e-3, "scene": {"position": [300, 3500]}},
        {"band": "Z087", "sca": 9, "precision": 0.02, "tolerance": 1e-3, "scene": {"position": [2000, 100]}},
    ],
)
def test_one_answer_checks_its_band_once(body, monkeypatch):
    answer(SolveRequest.from_json(body))  # what is read once per process (tables, backgrounds) is read
    calls = []
    check = roman.check_band

    def counted(band):
        calls.append(band)
        return check(band)

    monkeypatch.setattr(roman, "check_band", counted)
    answer(SolveRequest.from_json(body))
    assert calls == [body["band"]]


COLD = """
import json, sys
from nlpsf import SolveRequest, answer, roman
calls = []
check = roman.check_band
roman.check_band = lambda band: calls.append(band) or check(band)
answer(SolveRequest.from_json(json.loads(sys.argv[1])))
print(len(calls))
"""


def test_a_first_answer_checks_its_band_at_most_twice():
    # In a fresh process: once where the request comes in, once where the SCA's background is first
    # computed (roman.backgrounds, a public function that checks its own arguments; kept per SCA after).
    import json
    import subprocess
    import sys

    body = {"band": "W146", "sca": 7, "magnitude": 20.0, "tolerance": 1e-3}
    out = subprocess.run([sys.executable, "-c", COLD, json.dumps(body)], capture_output=True, text=True, check=True)
    assert int(out.stdout.strip().splitlines()[-1]) <= 2, out.stdout
