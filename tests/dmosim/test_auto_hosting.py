"""``agents.hosting = "auto"`` (the default) chooses how ``dmosim run`` hosts a fleet by its size
(dmosim/launch/roles.py, docs/benchmarks.md "Hosting agents"), and says what it chose in the run's experiment."""

from __future__ import annotations

import pytest

from dmosim.experiment.spec import Agents, ExperimentError, parse_experiment
from dmosim.launch.roles import FORKED_PROCESSES, PROCESSES_UP_TO, hosting_of


@pytest.mark.parametrize("count", [1, PROCESSES_UP_TO, PROCESSES_UP_TO + 1, FORKED_PROCESSES, 60, 1000])
def test_auto_hosts_a_small_fleet_as_processes_and_a_larger_one_forked_in_at_most_so_many_processes(count):
    hosting, per_process = hosting_of(Agents(), count)
    processes = -(-count // per_process)
    if count <= PROCESSES_UP_TO:
        assert (hosting, per_process) == ("process", 1)
    else:
        # as few to a process as keeps them within FORKED_PROCESSES processes
        assert hosting == "fork" and processes <= FORKED_PROCESSES and per_process == -(-count // FORKED_PROCESSES)
    # on a cluster each worker forks its agents one to a process
    assert hosting_of(Agents(), count, cluster=True) == (hosting, 1)


def test_a_hosting_given_is_kept_and_per_process_needs_fork():
    assert hosting_of(Agents(hosting="process"), 60) == ("process", 1)
    assert hosting_of(Agents(hosting="fork"), 60) == ("fork", 1)
    assert hosting_of(Agents(hosting="fork", per_process=7), 60) == ("fork", 7)
    for hosting in ("auto", "process"):
        with pytest.raises(ExperimentError, match="per_process = 3 needs hosting"):
            parse_experiment({"agents": {"hosting": hosting, "per_process": 3}})
