"""Zenoh for one run: the Bus every process opens, who may say and hear what (access.py, credentials.py),
message faults injected at a sender's bus (faults.py), and the memory a process freed given back (heap.py)."""

from .bus import MODES, Bus, BusConfig, Subscription, wait_matching

__all__ = ["MODES", "Bus", "BusConfig", "Subscription", "wait_matching"]
