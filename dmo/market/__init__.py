"""The market's rules, pure functions of what the DMO accepted: clearing (clearing.py), settlement (settlement.py)
and which messages are accepted (acceptance.py). The live DMO (operator/) and the replayed one (replay/) apply the
same ones."""
