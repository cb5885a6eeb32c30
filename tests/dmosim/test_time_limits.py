"""Default time limits leave room for a machine three times slower or as loaded (docs/solver.md, "Time limits")."""

from __future__ import annotations

import argparse
from pathlib import Path

from dmosim.cli import solve, study
from dmosim.experiment.spec import ScheduleSettings

ROOT = Path(__file__).resolve().parents[2]


def _defaults(module, *argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_solve_and_study_default_to_three_times_the_paper_days_seconds():
    assert solve.HEADROOM >= 3 and solve.TIME_LIMIT_S >= solve.HEADROOM * solve.PAPER_DAY_S
    paper = _defaults(study, "table2")  # a study's default instance is the paper's day
    assert (paper.scenarios, paper.subperiods) == (100, 6)
    assert _defaults(solve).time_limit == paper.time_limit == solve.TIME_LIMIT_S


def test_the_solver_doc_states_the_measured_seconds_and_the_default_the_code_has():
    text = (ROOT / "docs" / "solver.md").read_text()
    section = text.split("## Time limits", 1)[1].split("\n## ", 1)[0]
    assert f"{solve.PAPER_DAY_S:g} s" in section and f"{solve.TIME_LIMIT_S:,.0f} s" in section
    assert f"| {solve.PAPER_DAY_S:g} s (" in text.split("## The paper's day", 1)[1].split("\n## ", 1)[0]


def test_an_agent_in_a_run_has_no_time_limit_the_gap_alone_ends_its_solve():
    assert ScheduleSettings().time_limit is None

