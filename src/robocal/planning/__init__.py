"""robocal.planning."""
