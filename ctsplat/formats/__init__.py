"""File formats: sources, the volume file, view sets, PLY and run logs."""
