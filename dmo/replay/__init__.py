"""Recorded days, read back: re-settled from the recording alone (resettle.py), or played as the DMO to a live
agent (as_dmo.py)."""
