"""The BLAS thread limiter is re-entrant and restores the previous setting."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info

from robocal._core.threads import blas_threads, single_threaded


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_limit_inside_and_restored_after() -> None:
    np.linalg.svd(np.ones((4, 4)))  # make sure BLAS is loaded
    before = _blas_threads()
    assert before
    with blas_threads(1):
        assert set(_blas_threads()) == {1}
        with blas_threads(1):
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before

    @single_threaded
    def inner() -> list[int]:
        return _blas_threads()

    assert set(inner()) == {1}
    assert _blas_threads() == before
