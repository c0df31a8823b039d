"""What goes in and out of files: dumps, figures, schemas, calibration, meshes, trajectories (atomic writes:
wiredsl/files.py)."""
