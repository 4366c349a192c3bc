"""robocal.daemon."""
