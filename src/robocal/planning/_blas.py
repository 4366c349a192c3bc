"""Keep OpenBLAS single-threaded while planning does linear algebra.

Planning issues many small and medium BLAS/LAPACK calls (rank-3 Woodbury updates, a QR of a
few thousand rows, 6 x 6 solves in the IK). On a small machine shared with other processes,
multi-threaded OpenBLAS spends far more time synchronising than computing (measured here: a
QR of a 900 x 219 matrix took 0.2-5 s instead of 14 ms). Identification ships a limiter that
finds every OpenBLAS loaded in the process; use it when it is there, else do nothing.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any, ParamSpec, TypeVar

_limiter: Callable[[int], AbstractContextManager[Any]] | None
try:
    from robocal.identification._threads import blas_threads as _limiter
except ImportError:  # pragma: no cover - identification without it
    _limiter = None

P = ParamSpec("P")
R = TypeVar("R")


def blas_threads(n: int = 1) -> AbstractContextManager[Any]:
    """Limit OpenBLAS to ``n`` threads inside the block when possible."""
    if _limiter is None:  # pragma: no cover
        return contextlib.nullcontext()
    return _limiter(n)


def single_threaded(func: Callable[P, R]) -> Callable[P, R]:
    """Run ``func`` with OpenBLAS limited to one thread."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with blas_threads(1):
            return func(*args, **kwargs)

    return wrapper
