"""``dmosim bench NAME``: benchmarks that print ratios and absolute times measured side by side in one run.

Each benchmark module has ``add_arguments(parser)`` and ``run(args) -> dict``: the dict is printed as a table,
or as one JSON object with ``--json`` (dmosim/cli/bench.py). Never timed assertions in tests: figures belong here.
"""
