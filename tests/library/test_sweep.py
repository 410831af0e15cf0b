"""Sweeps: the same rows as `experiment.simulate`, resumable, on local processes or dask workers elsewhere."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from nlpsf import cli
from nlpsf.checks import InputError
from nlpsf.sim import cluster, experiment, sweep

SMALL = experiment.SimulationConfig(realizations=4, stamp=48)


def grid(**changes) -> sweep.SweepGrid:
    axes = {
        "bands": ("H158", "Y106"),
        "scas": (3, 7),
        "magnitudes": (19.0, 21.0),
        "betas": (5e-7, 1e-6),
        "sigma_betas": (0.0, 2e-8),
        "settings": SMALL,
    }
    return sweep.SweepGrid(**{**axes, **changes})


def assert_same_rows(a: Table, b: Table) -> None:
    """The same rows to float64 rounding: a dask worker runs BLAS on one thread (distributed sets
    OMP_NUM_THREADS=1) where the calling process may use several, which reorders the sums in the
    matrix products by a few ulp (seen: 4e-13 relative on Delta R / R, 4e-16 absolute on the spread
    over realizations, whose values are ~1e-2 apiece)."""
    assert a.colnames == b.colnames and len(a) == len(b)
    for name in a.colnames:
        if name == "elapsed_s":
            continue
        if a[name].dtype.kind == "f":
            np.testing.assert_allclose(np.asarray(a[name]), np.asarray(b[name]), rtol=1e-10, atol=1e-14, err_msg=name)
        else:
            assert list(a[name]) == list(b[name]), name


def test_rows_are_what_simulate_returns():
    g = grid(bands=("J129",), scas=(5,))
    table = sweep.sweep(g)
    expected = []
    for sigma_beta in g.sigma_betas:
        expected += experiment.simulate(g.config("J129", 5), g.magnitudes, g.betas, sigma_beta)
    assert len(table) == len(expected) == 8
    for row, result in zip(table, expected, strict=True):
        assert (row["magnitude"], row["beta"], row["sigma_beta"]) == (result.magnitude, result.beta, result.sigma_beta)
        assert row["dR_over_R"] == result.dR_over_R.mean and row["de2_std"] == result.de2.std
        assert row["flags"] == " | ".join(result.flags)
    assert table.meta["grid"]["magnitudes"] == [19.0, 21.0]


def test_an_interrupted_sweep_resumes_and_gives_the_same_table(tmp_path):
    g = grid()
    whole = sweep.sweep(g)

    class Interrupt(Exception):
        pass

    def stop_after_first(done, total, message):
        if done == 1 and message != "starting":
            raise Interrupt

    with pytest.raises(Interrupt):
        sweep.sweep(g, tmp_path, progress=stop_after_first)
    assert len(list(tmp_path.glob("sweep_*.ecsv"))) == 1
    (tmp_path / "sweep_Y106_SCA07.ecsv.tmp").write_text("half a file from a killed run")
    seen = []
    resumed = sweep.sweep(g, tmp_path, progress=lambda d, t, m: seen.append((d, m)))
    assert seen[0] == (1, "resumed") and len(seen) == 1 + 3  # only the three missing cells ran
    assert_same_rows(resumed, whole)
    # A cell written with other settings is recomputed, not reused.
    other = grid(settings=experiment.SimulationConfig(realizations=5, stamp=48))
    seen.clear()
    sweep.sweep(other, tmp_path, progress=lambda d, t, m: seen.append((d, m)))
    assert seen[0] == (0, "starting")


def test_local_processes_give_the_serial_table(tmp_path):
    g = grid(sigma_betas=(2e-8,))
    assert_same_rows(sweep.sweep(g, tmp_path, workers=2), sweep.sweep(g))


def _flaky(counter: str, fail_times: int) -> int:
    path = Path(counter)
    count = int(path.read_text()) if path.exists() else 0
    path.write_text(str(count + 1))
    if count < fail_times:
        raise OSError(f"transient failure {count + 1}")
    return count


@pytest.mark.parametrize("workers", [1, 2])
def test_tasks_are_retried_then_reported(tmp_path, workers):
    tasks = [(str(tmp_path / "a"), 2), (str(tmp_path / "b"), 5), (str(tmp_path / "c"), 0)]
    outcomes = {i: (r, e) for i, r, e in cluster.run_tasks(_flaky, tasks, workers=workers, retries=2)}
    assert outcomes[0] == (2, None) and outcomes[2] == (0, None)
    assert outcomes[1][0] is None and "transient failure 3" in str(outcomes[1][1])
    assert (tmp_path / "b").read_text() == "3"  # one try and two retries


def test_bad_grids_name_the_option(capsys):
    with pytest.raises(InputError) as info:
        grid(bands=("H158", "X999"))
    assert info.value.argument == "band"
    with pytest.raises(InputError) as info:
        grid(sigma_betas=(-1e-8,))
    assert info.value.argument == "sigma_beta"
    assert cli.main(["sweep", "--band", "H158", "--sca", "19"]) == 2
    assert "--sca" in capsys.readouterr().err
    assert cli.main(["sweep", "--dask", "tcp://x:1", "--scheduler-file", "s.json"]) == 2
    assert "--scheduler-file" in capsys.readouterr().err


def test_cli_sweep_writes_where_it_is_told_and_resumes(tmp_path, capsys):
    arguments = ["sweep", "--band", "H158", "--sca", "2", "--magnitude", "19", "--magnitude", "20", "--realizations", "3"]
    arguments += ["--stamp", "48", "--output", str(tmp_path / "cells"), "--to", str(tmp_path / "all.ecsv"), "--json"]
    assert cli.main(arguments) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["magnitude"] for r in rows] == [19.0, 20.0]
    assert Table.read(tmp_path / "all.ecsv")["dR_over_R"][0] == rows[0]["dR_over_R"]
    assert cli.main(arguments) == 0
    assert json.loads(capsys.readouterr().out) == rows


# --- dask.distributed: workers that run somewhere else ---------------------------------------------


@pytest.fixture
def remote_cluster(tmp_path):
    """A LocalCluster whose two workers run in a directory of their own, as remote workers would."""
    distributed = pytest.importorskip("dask.distributed")
    elsewhere = tmp_path / "worker-home"
    elsewhere.mkdir()
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as local,
        distributed.Client(local) as client,
    ):
        client.run(os.chdir, str(elsewhere))
        yield client, elsewhere


@pytest.mark.slow
def test_dask_workers_in_another_directory_give_the_serial_table(tmp_path, monkeypatch, remote_cluster):
    client, elsewhere = remote_cluster
    assert set(client.run(os.getcwd).values()) == {str(elsewhere)}
    home = tmp_path / "client"
    home.mkdir()
    monkeypatch.chdir(home)
    g = grid()
    table = sweep.sweep(g, "results", dask_address=client.scheduler.address)  # a path relative to the client
    assert_same_rows(table, sweep.sweep(g))
    assert sorted(p.name for p in (home / "results").iterdir()) == sorted(f"sweep_{b}_SCA{s:02d}.ecsv" for b, s in g.cells())
    assert list(elsewhere.iterdir()) == []  # nothing written on the workers' side


@pytest.mark.slow
def test_tables_build_on_dask_workers_in_another_directory(tmp_path, monkeypatch, remote_cluster):
    from nlpsf.slopes import tablebuild

    client, elsewhere = remote_cluster
    monkeypatch.chdir(tmp_path)
    settings = tablebuild.TableSettings(realizations=3, faint_limit=19.0)
    paths = tablebuild.build_tables("out", bands=["F184"], scas=[5, 6], settings=settings, dask_address=client.scheduler.address)
    assert sorted(p.name for p in paths) == ["slopes_F184_SCA05.ecsv", "slopes_F184_SCA06.ecsv"]
    assert all((tmp_path / "out" / p.name).exists() for p in paths)
    assert list(elsewhere.iterdir()) == []


@pytest.mark.slow
def test_a_sweep_survives_a_killed_worker(tmp_path, remote_cluster):
    client, _ = remote_cluster
    g = grid(bands=("H158", "Y106", "J129"), settings=experiment.SimulationConfig(realizations=40, stamp=64))
    killed: list[int] = []
    lock = threading.Lock()

    def kill_a_busy_worker(done, total, message):
        # After the first cell, kill (SIGKILL) a worker that is computing one: the scheduler must
        # re-run its cell on the other worker (or on the restarted one).
        with lock:
            if killed or message in ("starting", "resumed"):
                return
            busy = [address for address, keys in client.processing().items() if keys]
            if not busy:
                return
            pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
            os.kill(pid, 9)
            killed.append(pid)

    table = sweep.sweep(g, tmp_path, client=client, progress=kill_a_busy_worker)
    assert killed, "no worker was busy when the first cell finished; the test did not kill anything"
    assert_same_rows(table, sweep.sweep(g))
