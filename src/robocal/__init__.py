"""robocal: calibration of industrial robots with constant and joint-dependent error models."""

__version__ = "0.1.0"
__all__ = ["__version__"]
