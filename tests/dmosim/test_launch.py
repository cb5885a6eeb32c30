"""What the launcher makes of its roles' exits (dmosim/launch/local.py): a role still there once the DMO is done."""

from __future__ import annotations

import sys
from types import SimpleNamespace

from dmosim.launch.local import wait_for_run
from dmosim.launch.processes import Roles

DONE = [sys.executable, "-c", "pass"]
STAYS = [sys.executable, "-c", "import time; time.sleep(120)"]


def wait(roles: Roles) -> tuple[list[str], list[str]]:
    said: list[str] = []
    return wait_for_run(roles, SimpleNamespace(say=said.append), leave_s=0.5), said


def test_an_agent_restarted_after_the_run_ended_is_stopped_not_failed():
    with Roles() as roles:
        roles.start("mg1", STAYS)
        roles.restart("mg1")  # as a restart fault does: the new process waits for a DMO that has finished
        roles.start("mg2", DONE)
        roles.start("dmo", DONE)
        assert wait(roles) == ([], ["mg1 restarted after the run had ended: stopped"])


def test_an_agent_that_does_not_leave_after_the_run_has_failed():
    with Roles() as roles:
        roles.start("mg1", STAYS)
        roles.start("dmo", DONE)
        assert wait(roles) == (["mg1"], [])
