"""The market operator and the application: the market's pure rules (market/), the DMO process (operator/),
recorded days read back (replay/), the processes of a run on this machine (launch/), the ``dmosim`` command line
(cli/) and the benchmarks (bench/). The top of the import flow: it may import the other three packages."""
