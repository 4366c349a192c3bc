"""robocal.report."""
