"""The API never opens a file by a name it was given (issue 19, item 1).

``nlpsf serve`` runs, as a real process with two HTTP workers on 127.0.0.1, in a folder holding what
an attacker wants read: a ``.env``, MA-table-shaped JSON under names the API takes (one named like a
shipped table), a directory and a large sparse file. Every name that is not a shipped table gets
the same 422, word for word; a shipped name answers from the package's own data, never from the
folder; nothing in the folder shows up in any answer.
"""

from __future__ import annotations

import json
import os
import signal

import httpx
import pytest

from nlpsf.sim import ramps

from ..servers import free_port, start_server

pytestmark = pytest.mark.slow

#: What a file in the server's folder says if it is ever read: no answer may contain it.
LEAK = "LEAKED-FROM-THE-SERVER-FOLDER"
MA_SHAPED = {"name": LEAK, "resultants": [[1], [2, 3]], "frame_time_s": 3.04, "source": LEAK}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    folder = tmp_path_factory.mktemp("attacker-folder")
    (folder / ".env").write_text(json.dumps(MA_SHAPED))
    (folder / "table").write_text(json.dumps(MA_SHAPED))
    (folder / "table.json").write_text(json.dumps(MA_SHAPED))
    shipped = ramps.shipped_table_names()
    (folder / shipped[0]).write_text(json.dumps(MA_SHAPED))  # a file named like a shipped table
    (folder / shipped[-1]).mkdir()  # and a directory
    (folder / "adirectory").mkdir()
    with open(folder / "big", "wb") as handle:  # 1 GB, sparse: costs no disk, would cost a worker its memory
        handle.truncate(1 << 30)
    (folder / "sed.txt").write_text("500 1\n600 1\n700 1\n")
    (folder / "ipc.txt").write_text("0 0.02 0\n0.02 0.92 0.02\n0 0.02 0\n")
    port = free_port()
    process = start_server(tmp_path_factory.mktemp("db") / "jobs.sqlite3", port, cwd=folder, args=("--workers", "2"))
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=20) as client:
            yield client, shipped, folder
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(30)


UNKNOWN = [".env", "table", "table.json", "adirectory", "big", "./table", "../table", "/etc/hostname", "x" * 300, "", "nosuch"]


def test_every_unknown_ma_table_name_gets_the_same_422(server):
    client, _, _ = server
    bodies = []
    for name in UNKNOWN:
        for path, body in (
            ("/api/v1/solve", {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "ma_table": name}),
            ("/api/v1/simulations", {"realizations": 2, "stamp": 32, "ma_table": name}),
        ):
            response = client.post(path, json=body)
            assert response.status_code == 422, (name, response.text[:300])
            assert LEAK not in response.text
            problem = response.json()
            assert problem["field"] == "ma_table"
            bodies.append(problem["detail"])
    assert len(set(bodies)) == 1, set(bodies)  # nothing tells a missing name from a directory or a file


def test_a_batch_row_with_a_bad_name_fails_alone(server):
    client, _, _ = server
    good = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}
    response = client.post("/api/v1/solve/batch", json={"requests": [good, {**good, "ma_table": "x" * 300}, good]})
    assert response.status_code == 200
    answer = response.json()
    assert [r["ok"] for r in answer["results"]] == [True, False, True]
    assert answer["results"][1]["error"]["field"] == "ma_table"


def test_shipped_names_come_from_the_package_not_the_folder(server):
    client, shipped, _ = server
    meta = client.get("/api/v1/meta").json()
    assert [t["name"] for t in meta["ma_tables"]] == shipped
    assert LEAK not in json.dumps(meta)
    for name in (shipped[0], shipped[-1], shipped[0].upper()):
        response = client.post(
            "/api/v1/solve", json={"band": "H158", "magnitude": 20.0, "tolerance": 1e-4, "ma_table": name, "fidelity": "table"}
        )
        assert LEAK not in response.text
        # A table solve with a ramp is a job: accepted (202/200) or refused for a reason of its own, never a file's.
        assert response.status_code in (200, 202), response.text[:300]


def test_scene_names_never_reach_the_folder(server):
    client, _, _ = server
    for scene in ({"sed": "sed.txt"}, {"ipc": "ipc.txt"}, {"sed": ".env"}, {"ipc": "big"}):
        response = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": scene})
        assert response.status_code == 422, response.text[:300]
    response = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "size_ratio": "@.env"})
    assert response.status_code == 422


def test_the_big_file_was_never_read(server):
    """Had a worker read the 1 GB file, its resident memory would have grown by about that much."""
    client, _, folder = server
    assert client.get("/api/v1/health").status_code == 200
    workers = [int(p) for p in os.listdir("/proc") if p.isdigit() and _cwd(int(p)) == str(folder)]
    assert workers
    for pid in workers:
        with open(f"/proc/{pid}/status") as handle:
            rss_kb = next(int(line.split()[1]) for line in handle if line.startswith("VmHWM:"))
        assert rss_kb < 900 * 1024, (pid, rss_kb)


def _cwd(pid: int) -> str | None:
    try:
        return os.readlink(f"/proc/{pid}/cwd")
    except OSError:
        return None
