"""Keep OpenBLAS single-threaded during identification.

Identification issues thousands of small and medium BLAS/LAPACK calls (per-fold Cholesky
solves, Schur complements). On a machine with few cores that is shared with other processes,
multi-threaded OpenBLAS spends far more time synchronising its threads than computing (a
20x slow-down was measured on a busy 2-core machine). :func:`blas_threads` limits every
OpenBLAS library loaded in the process (numpy's and scipy's) for the duration of a block and
restores the previous setting afterwards. Without OpenBLAS it does nothing. The limit is
process-global while the block runs.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
            "openblas_set_num_threads64_", "openblas_set_num_threads")
_GETTERS = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
            "openblas_get_num_threads64_", "openblas_get_num_threads")
_lock = threading.RLock()
_libs: list[tuple[ctypes.CDLL, str, str]] | None = None
_depth = 0
_saved: list[int] = []


def _find() -> list[tuple[ctypes.CDLL, str, str]]:
    global _libs
    if _libs is not None:
        return _libs
    found: list[tuple[ctypes.CDLL, str, str]] = []
    try:
        import numpy  # noqa: F401  (make sure the libraries are loaded)
        import scipy.linalg  # noqa: F401

        paths = sorted({line.split()[-1] for line in Path("/proc/self/maps").read_text()
                        .splitlines() if "openblas" in line.lower() and "/" in line})
    except (OSError, ImportError):
        paths = []
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        setter = next((s for s in _SETTERS if hasattr(lib, s)), None)
        getter = next((g for g in _GETTERS if hasattr(lib, g)), None)
        if setter and getter:
            found.append((lib, setter, getter))
    _libs = found
    return found


@contextmanager
def blas_threads(n: int = 1) -> Iterator[None]:
    """Limit OpenBLAS to ``n`` threads inside the block (re-entrant)."""
    global _depth, _saved
    with _lock:
        libs = _find()
        if _depth == 0:
            _saved = []
            for lib, setter, getter in libs:
                _saved.append(int(getattr(lib, getter)()))
                getattr(lib, setter)(ctypes.c_int(n))
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                for (lib, setter, _), old in zip(libs, _saved, strict=True):
                    getattr(lib, setter)(ctypes.c_int(old))
