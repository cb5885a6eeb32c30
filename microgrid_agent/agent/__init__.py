"""The microgrid agent process: its market day on the bus (process.py), its bids (bidding.py) and its real-time
operation through the realised day (realtime.py)."""
