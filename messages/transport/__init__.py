"""Zenoh for one run: the Bus every process opens, who may say and hear what (access.py, credentials.py), and
message faults injected at a sender's bus (faults.py)."""

from .bus import MODES, Bus, BusConfig, Subscription

__all__ = ["MODES", "Bus", "BusConfig", "Subscription"]
