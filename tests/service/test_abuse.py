"""The service under abuse (issue 26), in process: what a hostile or careless client sends is answered
2xx or 4xx, parsed in linear time, budgeted per client and never the cause of another's 5xx.

Real servers (the README's start, proxies) are in ``test_serving.py``; the victim's latency under
attack is a benchmark (``benchmarks/bench_abuse.py``), not a test."""

from __future__ import annotations

import gzip
import json
import math

import pytest
from nlpsf.web import budget, security

from nlpsf.slopes import fieldgrid, tables

DEFAULT = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}
PAPER = {**DEFAULT, "scene": "paper"}


# --- bodies: linear parsing, compression, byte-order marks -------------------------------------------


def _keys_body(count: int, repeat: str | None = None) -> bytes:
    letters = "abcdefghijklmnopqrstuvwxyz"
    keys = [a + b + c for a in letters for b in letters for c in letters][:count]
    parts = [f'"{k}":1' for k in keys] + ([f'"{repeat}":2'] if repeat else [])
    return ("{" + ",".join(parts) + "}").encode()


def test_duplicate_keys_are_found_in_every_object():
    for count in (1000, 8000):
        assert security.duplicate_keys(_keys_body(count, repeat="aab")) == "aab"
        assert security.duplicate_keys(_keys_body(count)) is None
    assert security.duplicate_keys(b'{"a": {"x": 1, "y": 2, "x": 3}, "b": 1}') == "x"
    assert security.duplicate_keys(b'[{"a": 1}, {"a": 2}]') is None  # the same key in two objects
    assert security.duplicate_keys(b"not json") is None
    assert security.duplicate_keys(b"[" * 40_000) is None  # too deep for the parser: the app says what is wrong


def test_a_large_body_with_a_repeated_key_is_refused_naming_it(client):
    body = _keys_body(8000, repeat="aab")
    assert len(body) > 60_000
    refused = client.post("/api/v1/solve", content=body, headers={"Content-Type": "application/json"})
    assert refused.status_code == 422 and "'aab'" in refused.json()["detail"]
    # A large body without a repeated key reaches the schema, which names the unknown fields.
    unknown = client.post("/api/v1/solve", content=_keys_body(8000), headers={"Content-Type": "application/json"})
    assert unknown.status_code == 422 and unknown.json()["type"] == "/problems/invalid-input"


def test_a_compressed_body_is_refused_never_read_as_text(client):
    packed = gzip.compress(json.dumps(PAPER).encode())
    for encoding in ("gzip", "deflate", "br"):
        refused = client.post(
            "/api/v1/solve", content=packed, headers={"Content-Type": "application/json", "Content-Encoding": encoding}
        )
        assert refused.status_code == 415, encoding
        assert refused.headers["accept-encoding"] == "identity" and refused.json()["status"] == 415
    plain = client.post("/api/v1/solve", json=PAPER, headers={"Content-Encoding": "identity"})
    assert plain.status_code == 200


def test_a_byte_order_mark_is_dropped_from_csv_and_json_bodies(client):
    csv_text = "band,precision,magnitude\nH158,0.01,19\n"
    plain = client.post("/api/v1/page/batch", content=csv_text, headers={"Content-Type": "text/csv"}).json()
    marked = client.post(
        "/api/v1/page/batch", content=b"\xef\xbb\xbf" + csv_text.encode(), headers={"Content-Type": "text/csv"}
    ).json()
    assert marked["results"][0]["ok"] and marked["results"] == plain["results"]
    body = b"\xef\xbb\xbf" + json.dumps(PAPER).encode()
    answer = client.post("/api/v1/solve", content=body, headers={"Content-Type": "application/json"})
    expected = client.post("/api/v1/solve", json=PAPER).json()["precision"]
    assert answer.status_code == 200 and answer.json()["precision"] == expected


# --- every valid request 2xx or 4xx ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"ramp": 1}, "ramp"),
        ({"ramp": 1, "scene": "paper"}, "ramp"),
        ({"ramp": 1, "scene": {"position": [100, 100]}}, "ramp"),
        ({"ma_table": {"resultants": [[1]], "frame_time_s": 3.04}}, "ma_table"),
        ({"ma_table": {"resultants": [[1, 2, 3]], "frame_time_s": 3.04}}, "ma_table"),
    ],
)
def test_a_one_resultant_ramp_is_refused_naming_the_rule(client, extra, field):
    refused = client.post("/api/v1/solve", json={**DEFAULT, **extra})
    assert refused.status_code == 422, refused.text
    problem = refused.json()
    assert problem["field"] == field and "'unusable'" in problem["detail"] and "two resultants" in problem["detail"]
    # The same in a batch entry, and for a simulation.
    entry = client.post("/api/v1/solve/batch", json={"requests": [{**DEFAULT, **extra}]}).json()["results"][0]
    assert not entry["ok"] and entry["error"]["field"] == field
    job = {"band": "H158", "magnitudes": [19.0], "betas": [5e-7], "realizations": 3, **extra}
    job.pop("scene", None)
    assert client.post("/api/v1/simulations", json=job).status_code == 422


def test_a_one_resultant_table_answers_where_one_resultant_gives_a_slope():
    # The library under the rule that fits one resultant through zero: the final frame's limit.
    from nlpsf.checks import InputError
    from nlpsf.sim import ramps

    one = ramps.Ramp.uniform(1, 139.149, single_resultant="through_zero")
    assert one.saturation_shift_mag(139.149, 1.1e5, 5e-7, 50.0) == pytest.approx(0.0, abs=0.1)
    with pytest.raises(InputError, match="unusable"):
        ramps.Ramp.uniform(1, 139.149).saturation_shift_mag(139.149, 1.1e5, 5e-7, 50.0)


def test_a_csv_batch_over_the_row_limit_is_a_422(client):
    rows = "band,precision,magnitude\n" + "H158,0.01,19\n" * 1001
    refused = client.post("/api/v1/page/batch", content=rows, headers={"Content-Type": "text/csv"})
    assert refused.status_code == 422 and refused.json()["field"] == "requests"
    too_many = client.post(
        "/api/v1/solve/batch", json={"requests": [{"band": "H158", "precision": 0.01, "magnitude": 19}] * 1001}
    )
    assert too_many.status_code == 422


def test_a_server_error_names_no_internal_class(client, monkeypatch):
    from nlpsf.solve import solver

    def broken(*args, **kwargs):
        raise KeyError("an internal detail")

    monkeypatch.setattr(solver, "answer", broken)
    from fastapi.testclient import TestClient

    with TestClient(client.app, raise_server_exceptions=False) as quiet:
        failed = quiet.post("/api/v1/solve", json=PAPER)
    assert failed.status_code == 500
    assert "KeyError" not in failed.text and "internal detail" not in failed.text
    entry = client.post("/api/v1/solve/batch", json={"requests": [PAPER]}).json()["results"][0]
    assert entry["error"]["status"] == 500 and "KeyError" not in json.dumps(entry)


# --- the tables: once per process, compressed, validators, HEAD ----------------------------------------


def test_the_tables_are_built_once_and_sent_compressed_with_validators(client):
    documents = client.app.state.documents
    first = client.get("/api/v1/tables", headers={"Accept-Encoding": "gzip"})
    assert first.status_code == 200 and first.headers["content-encoding"] == "gzip"
    assert first.headers["vary"] == "Accept-Encoding"
    built = documents.peek(("tables", "json", None, None))
    assert built is not None and built.gzipped and int(first.headers["content-length"]) == len(built.gzipped)
    again = client.get("/api/v1/tables", headers={"Accept-Encoding": "gzip"})
    assert documents.peek(("tables", "json", None, None)) is built and again.content == first.content
    assert len(first.json()["rows"]) == len(tables.table_rows(None, None))
    plain = client.get("/api/v1/tables", headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.content == built.body
    not_modified = client.get("/api/v1/tables", headers={"If-None-Match": first.headers["etag"]})
    assert not_modified.status_code == 304 and not not_modified.content
    head = client.head("/api/v1/tables", headers={"Accept-Encoding": "gzip"})
    assert head.status_code == 200 and not head.content and head.headers["etag"] == first.headers["etag"]
    assert head.headers["content-length"] == first.headers["content-length"]


def test_head_does_not_build_a_document(client):
    documents = client.app.state.documents
    assert documents.peek(("tables", "csv", "J129", 7)) is None
    head = client.head("/api/v1/tables.csv", params={"band": "J129", "sca": 7})
    assert head.status_code == 200 and head.headers["etag"] and not head.content
    assert documents.peek(("tables", "csv", "J129", 7)) is None
    got = client.get("/api/v1/tables.csv", params={"band": "J129", "sca": 7})
    assert got.status_code == 200 and got.headers["etag"] == head.headers["etag"]
    assert documents.peek(("tables", "csv", "J129", 7)) is not None


# --- inline work budgeted per client ------------------------------------------------------------------


def _defaults(count: int, start: int = 0, band: str = "H158") -> list[dict]:
    """Distinct Roman-default solves without a position (each reads every node of the SCA)."""
    return [{"band": band, "magnitude": round(19.0 + 0.0001 * k, 4), "tolerance": 1e-4} for k in range(start, start + count)]


#: W146's SCAs hold 5 x 5 field-grid nodes (H158's 3 x 3): a row there costs 25 node reads.
W146_NODES = 25


def _node_cost(client) -> float:
    """What a field-grid node costs this process (CPU s), measured: the budget's own cost model."""
    client.post("/api/v1/solve/batch", json={"requests": _defaults(20, start=90_000)})
    return budget.COSTS.per_unit(budget.NODE)


def test_a_client_past_its_share_of_inline_cpu_gets_429_with_retry_after(client, make_client):
    # Batches sized from the measured cost (the budget follows the code's speed): each estimated at
    # ten times what is never refused, the burst two and a half of them, refilled at a trickle.
    node = _node_cost(client)
    rows = max(1, min(400, math.ceil(10 * budget.FREE_S / (9 * node))))
    estimate = rows * 9 * node
    keys = ["client-a-key-0123456789", "client-b-key-0123456789"]
    with make_client(api_keys=",".join(keys), inline_cpu_share=1e-6, inline_cpu_total_share=1e-6,
                     inline_cpu_burst_s=2.5 * estimate) as tight:  # fmt: skip
        a, b = ({"X-API-Key": key} for key in keys)
        statuses = []
        for k in range(10):
            response = tight.post("/api/v1/solve/batch", json={"requests": _defaults(rows, start=1000 * k)}, headers=a)
            statuses.append(response.status_code)
            if response.status_code == 429:
                break
        assert statuses[0] == 200 and statuses[-1] == 429, statuses
        problem = response.json()
        assert problem["limit"] == "inline_cpu_share" and problem["type"] == "/problems/inline-cpu-used"
        assert int(response.headers["Retry-After"]) >= 1
        # An answer already given is a look-up, and a table solve costs (almost) nothing: neither is refused.
        assert tight.post("/api/v1/solve", json=_defaults(1)[0], headers=a).status_code == 200
        assert tight.post("/api/v1/solve", json=PAPER, headers=a).status_code == 200
        # Another client has its own share (all clients together have another, which A has not used up).
        assert tight.post("/api/v1/solve/batch", json={"requests": _defaults(rows, start=50_000)}, headers=b).status_code == 200


def test_a_batch_is_budgeted_by_its_rows_cost_not_its_row_count(client, make_client):
    node = _node_cost(client)
    # The burst: reading a thousand rows (each row's reading is work too, measured like a node's) and
    # fifty rows' answers, far less than a thousand answers. W146 rows (25 nodes each): a node now costs
    # about what reading a row does, so H158's nine did not leave the margin on every machine.
    row = budget.COSTS.per_unit(budget.ROW)
    burst = max(0.01, 3 * 1000 * row + W146_NODES * node * 50)
    assert 1000 * W146_NODES * node > 2 * burst, (node, row)
    with make_client(inline_cpu_burst_s=burst) as tight:
        # A thousand distinct default rows: every node of the SCA each, far more than one client's budget.
        refused = tight.post("/api/v1/solve/batch", json={"requests": _defaults(1000, band="W146")})
        assert refused.status_code == 422 and refused.json()["limit"] == "inline_cpu_burst_s"
        csv_text = "band,tolerance,magnitude\n" + "".join(f"W146,1e-4,{19 + 0.0001 * k:.4f}\n" for k in range(1000))
        csv_refused = tight.post("/api/v1/page/batch", content=csv_text, headers={"Content-Type": "text/csv"})
        assert csv_refused.status_code == 422 and csv_refused.json()["limit"] == "inline_cpu_burst_s"
    with make_client(inline_cpu_burst_s=burst) as tight:
        # As many rows, all the same: their reading and one answer's cost.
        same = tight.post("/api/v1/solve/batch", json={"requests": _defaults(1, band="W146") * 1000})
        assert same.status_code == 200, same.text[:300]


def test_a_costly_page_answer_is_budgeted_and_a_repeated_one_kept(make_client):
    with make_client(inline_cpu_share=1e-6, inline_cpu_total_share=1e-6, inline_cpu_burst_s=0.01) as tight:
        asked = [{**DEFAULT, "tolerance": 1e-4 * (1 + k / 10)} for k in range(4)]
        answers = [tight.post("/api/v1/page/requirement", json=body) for body in asked]
        statuses = [a.status_code for a in answers]
        assert statuses[0] == 200 and statuses[-1] == 429, statuses
        # The first answer is kept: asked again, it costs nothing and is the same answer, with a validator.
        again = tight.post("/api/v1/page/requirement", json=asked[0])
        assert again.status_code == 200 and again.json() == answers[0].json() and again.headers["etag"]
        revalidated = tight.post("/api/v1/page/requirement", json=asked[0], headers={"If-None-Match": again.headers["etag"]})
        assert revalidated.status_code == 304


def test_cached_answers_are_the_answers(client):
    first = client.post("/api/v1/solve", json=DEFAULT).json()
    again = client.post("/api/v1/solve", json=DEFAULT).json()
    assert again == first
    entry = client.post("/api/v1/solve/batch", json={"requests": [DEFAULT]}).json()["results"][0]
    assert entry["solution"] == first
    curves = [client.get("/api/v1/curves/slope", params={"metric": "e1"}) for _ in range(2)]
    assert curves[0].json() == curves[1].json() and curves[0].headers["content-type"] == curves[1].headers["content-type"]
    download = [client.get("/api/v1/page/tables.csv") for _ in range(2)]
    assert download[0].text == download[1].text and download[1].headers["content-disposition"].startswith("attachment")


def test_a_default_solve_costs_its_nodes():
    from nlpsf.web.solve_api import units_of

    from nlpsf.request.resolve import SolveRequest
    from nlpsf.solve.over_field import range_positions

    request = SolveRequest.from_json(DEFAULT)
    assert units_of(request) == (budget.NODE, float(len(range_positions(request))))
    at = SolveRequest.from_json({**DEFAULT, "scene": {"position": [2000, 2000]}})
    assert units_of(at) == (budget.NODE, 1.0)
    assert units_of(SolveRequest.from_json(PAPER)) == (budget.TABLE, 1.0)
    assert fieldgrid.shipped_grid() is None or len(range_positions(request)) > 1


def test_buckets_refill_at_the_share_and_cap_at_the_burst():
    buckets = budget.Buckets(rate=0.5, burst=2.0)
    assert buckets.balance("a", 0.0) == 2.0
    buckets.set("a", -1.0, 10.0)
    assert buckets.balance("a", 12.0) == pytest.approx(0.0) and buckets.wait_s("a", 1.0, 12.0) == pytest.approx(2.0)
    assert buckets.balance("a", 100.0) == 2.0
    model = budget.CostModel()
    model.observe("node", 9, 0.09)
    assert model.estimate("node", 9) == pytest.approx(0.09)
    model.observe("node", 1, 0.02)
    assert 0.01 < model.per_unit("node") < 0.02


def test_turns_go_one_at_a_time_round_the_clients_and_leave_nothing_behind():
    # The documented order: one turn at a time per worker, each client's requests in its own line
    # first -- a second request of a client holding the turn waits behind another client's first.
    import asyncio

    async def run() -> tuple[list[str], int]:
        turns, held, order = budget.Turns(), [], []

        async def request(client: str, name: str) -> None:
            async with turns.turn(client):
                held.append(name)
                assert len(held) == 1  # nobody else holds a turn
                order.append(name)
                await asyncio.sleep(0.01)
                held.remove(name)

        first = asyncio.create_task(request("a", "a1"))
        await asyncio.sleep(0)  # a1 takes the free turn
        rest = [asyncio.create_task(request(c, n)) for c, n in (("a", "a2"), ("b", "b1"))]
        await asyncio.gather(first, *rest)
        async with turns.turn("c"):  # free again: taken at once
            order.append("c1")
        return order, len(turns._lines)

    order, lines = asyncio.run(run())
    assert order == ["a1", "b1", "a2", "c1"] and lines == 0


# --- keys guard the schema and the docs ----------------------------------------------------------------


def test_a_keyed_service_keys_its_schema_and_docs(make_client):
    key = "client-a-key-0123456789"
    with make_client(api_keys=key) as client:
        for path in ("/openapi.json", "/docs", "/docs.html"):
            assert client.get(path).status_code == 401, path
            assert client.get(path, headers={"X-API-Key": key}).status_code == 200, path
        assert client.get("/").status_code == 200  # the page itself
        assert client.get("/api/v1/health").status_code == 200  # probes


def test_a_band_asked_many_times_is_one_curve(client):
    # 1,000 repeats of one band were 1,000 curves (3 MB); now as many curves as distinct bands.
    once = client.get("/api/v1/curves/slope", params={"bands": "H158"})
    repeated = client.get("/api/v1/curves/slope", params=[("bands", "H158")] * 1000 + [("bands", "J129")])
    assert once.status_code == repeated.status_code == 200
    assert [c["band"] for c in repeated.json()["curves"]] == ["H158", "J129"]
    assert repeated.json()["curves"][0] == once.json()["curves"][0]
