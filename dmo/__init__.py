"""The market operator: the market's pure rules (market/), the DMO process (operator/) and recorded days read
back (replay/). It may import scenarios, messages and microgrid_agent; the application (dmosim) imports it."""
