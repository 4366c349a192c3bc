"""robocal.cli."""
