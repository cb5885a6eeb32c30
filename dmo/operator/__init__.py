"""The DMO process: its market day (day.py) and the units it is built from: configuration (config.py), state
(state.py), the replay guard (guard.py), the incident log (incidents.py), the journal (journal.py), rejoining agents
(rejoin.py) and the messages it publishes (outbox.py)."""
