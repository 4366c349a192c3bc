"""The OpenBLAS thread limiter restores the previous setting."""

from __future__ import annotations

from robocal.identification import _threads


def test_blas_threads_is_reentrant_and_restores():
    libs = _threads._find()
    before = [int(getattr(lib, g)()) for lib, _, g in libs]
    with _threads.blas_threads(1):
        assert all(int(getattr(lib, g)()) == 1 for lib, _, g in libs)
        with _threads.blas_threads(1):
            pass
        assert all(int(getattr(lib, g)()) == 1 for lib, _, g in libs)
    assert [int(getattr(lib, g)()) for lib, _, g in libs] == before
