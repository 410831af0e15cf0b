"""The simulation kernels run on one BLAS thread unless NLPSF_BLAS_THREADS says otherwise.

The truth is the BLAS library's own thread count (threadpoolctl asks OpenBLAS), read from inside a
real kernel through its progress callback.
"""

from __future__ import annotations

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from nlpsf import InputError, threads
from nlpsf.sim import experiment


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():
    """Start from two BLAS threads whatever the machine, so that a limit to one shows."""
    if not _blas_threads():
        pytest.skip("no BLAS library threadpoolctl can control")
    with threadpool_limits(limits=2, user_api="blas"):
        yield


def _threads_inside_a_kernel() -> set[int]:
    seen: set[int] = set()
    config = experiment.SimulationConfig(band="H158", realizations=4, stamp=32)
    experiment.prepare(config, progress=lambda *_: seen.update(_blas_threads()))
    return seen


def test_a_kernel_runs_on_one_blas_thread_and_gives_the_callers_setting_back(two_blas_threads, monkeypatch):
    monkeypatch.delenv(threads.VARIABLE, raising=False)
    assert set(_blas_threads()) == {2}
    assert _threads_inside_a_kernel() == {1}
    assert set(_blas_threads()) == {2}


def test_the_setting_chooses_the_threads_and_zero_leaves_blas_alone(two_blas_threads, monkeypatch):
    monkeypatch.setenv(threads.VARIABLE, "3")
    assert _threads_inside_a_kernel() == {3}
    monkeypatch.setenv(threads.VARIABLE, "0")
    assert _threads_inside_a_kernel() == {2}
    assert set(_blas_threads()) == {2}


def test_nested_kernels_keep_the_outer_limit_until_the_outermost_returns(two_blas_threads, monkeypatch):
    monkeypatch.delenv(threads.VARIABLE, raising=False)
    with threads.limited_blas():
        assert set(_blas_threads()) == {1}
        with threads.limited_blas():
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert set(_blas_threads()) == {2}


@pytest.mark.parametrize("text", ["-1", "two", "1.5"])
def test_a_bad_setting_is_an_input_error_naming_the_variable(monkeypatch, text):
    monkeypatch.setenv(threads.VARIABLE, text)
    with pytest.raises(InputError) as error:
        threads.blas_threads()
    assert error.value.argument == threads.VARIABLE


def test_a_kernel_that_raises_still_restores_the_setting(two_blas_threads, monkeypatch):
    monkeypatch.delenv(threads.VARIABLE, raising=False)

    @threads.single_blas
    def failing():
        raise RuntimeError("inside")

    with pytest.raises(RuntimeError):
        failing()
    assert set(_blas_threads()) == {2}
