"""Recorded market days as results: tidy pandas tables of a recording (tables.py) and its figure (figures.py), behind
the verbs ``dmosim export`` and ``dmosim plot``."""
