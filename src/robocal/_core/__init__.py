"""Foundations shared by every layer (no device I/O): measurement sets and CSV files
(:mod:`~robocal._core.measurements`), file writing and TOML reading (:mod:`~robocal._core.files`),
clocks, BLAS threads and the error-model names (:mod:`~robocal._core.model_names`).

The package itself imports nothing, so that light modules (the model names) stay free of
numpy; import from the modules.
"""
