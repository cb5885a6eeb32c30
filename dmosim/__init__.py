"""The application: what composes the four packages into the ``dmosim`` tool: the command line (cli/),
experiments (experiment/), a run's processes on this machine (launch/), results (results/), benchmarks (bench/)
and the paper's studies (studies/). The top of the import flow: it may import every other package."""
