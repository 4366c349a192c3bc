"""robocal.identification."""
