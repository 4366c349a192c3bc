"""Keep BLAS single-threaded inside numerical blocks.

robocal issues many small and medium BLAS/LAPACK calls (per-fold Cholesky solves, rank-3
updates, 6 x 6 solves, SVDs of a few hundred columns). On a small cell PC shared with other
processes, a multi-threaded OpenBLAS spends far more time synchronising its threads than
computing: 20-200x slow-downs were measured on a busy 2-core machine. The limit is applied
with threadpoolctl to every BLAS loaded in the process and restored on exit.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

P = ParamSpec("P")
R = TypeVar("R")
_lock = threading.RLock()
_depth = 0


@contextmanager
def blas_threads(n: int = 1) -> Iterator[None]:
    """Limit BLAS to ``n`` threads inside the block (re-entrant; outermost block wins)."""
    global _depth
    with _lock:
        _depth += 1
        outer = _depth == 1
    try:
        if outer:
            with threadpool_limits(limits=n, user_api="blas"):
                yield
        else:
            yield
    finally:
        with _lock:
            _depth -= 1


def single_threaded(func: Callable[P, R]) -> Callable[P, R]:
    """Decorator: run ``func`` with BLAS limited to one thread."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with blas_threads(1):
            return func(*args, **kwargs)

    return wrapper
