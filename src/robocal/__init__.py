"""robocal: calibration of industrial robots with constant and joint-dependent error models."""

from __future__ import annotations

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    # The one source of the version is the package metadata (pyproject.toml). Looked up on
    # first use: importlib.metadata costs more than the CLI's whole start-up budget.
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("robocal")
        except PackageNotFoundError:  # pragma: no cover - a source tree never installed
            value = "0+unknown"
        globals()["__version__"] = value
        return value
    raise AttributeError(f"module 'robocal' has no attribute {name!r}")
