"""Keep OpenBLAS single-threaded while the report does linear algebra.

On a small machine shared with other processes, multi-threaded OpenBLAS can be 20-200 times
slower than one thread for the report's medium-size products and SVDs (measured: an SVD of
a 588 x 147 matrix took 1.4 s instead of 7 ms on a busy 2-core machine). Identification
ships the limiter; use it when it is there, else do nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any

_limiter: Callable[[int], AbstractContextManager[Any]] | None
try:  # identification's limiter (it finds every OpenBLAS loaded in the process)
    from robocal.identification._threads import blas_threads as _limiter
except ImportError:  # pragma: no cover - identification without it
    _limiter = None


def blas_threads(n: int = 1) -> AbstractContextManager[Any]:
    """Limit OpenBLAS to ``n`` threads inside the block when possible."""
    if _limiter is None:
        return contextlib.nullcontext()
    return _limiter(n)
