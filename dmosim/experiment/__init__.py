"""Experiments: the file that fixes a run (spec.py), and where a run leaves what it made (rundir.py)."""
