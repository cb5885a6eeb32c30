"""Recorded days, read back: re-settled from the recording alone (resettle.py), or run as the market of the DMO's
machine with a live agent taking part (recorded.py)."""
