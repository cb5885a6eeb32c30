"""A decomposed solve takes the same path on one core as on two (docs/solver.md, "The same path on every machine"):
HiGHS's thread count is pinned (``microgrid_agent.solvers.highs.HIGHS_THREADS``), where its default would run each
MILP master with as many workers as the cores the process may use, and search another tree on each."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from test_market_day import ENV, ROOT, dmosim, ended

pytestmark = pytest.mark.slow

# Benders forced on an hourly day whose certifying master branches (7 nodes): with HiGHS's default thread count it
# took 7 nodes and 7,647 simplex iterations under `taskset -c 0` and 3 nodes and 7,934 on both cores. About 6 s.
SOLVE = ["solve", "--case", "paper", "--scenarios", "12", "--subperiods", "1", "--seed", "1", "--method", "benders",
         "--json"]


def solved(cpus: str) -> dict:
    out = ended(["taskset", "-c", cpus, *dmosim(*SOLVE)], timeout=300, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout)


def path(result: dict):
    """Everything a solve reports but its seconds: the schedule, and each iteration's bounds (floats read back from
    JSON are the bits written), simplex iterations and nodes."""
    if isinstance(result, dict):
        return {k: path(v) for k, v in result.items() if k != "timings" and not k.endswith("_s")}
    if isinstance(result, list):
        return [path(v) for v in result]
    return result


@pytest.mark.skipif(shutil.which("taskset") is None, reason="taskset (util-linux) is not installed")
@pytest.mark.skipif(not {0, 1} <= os.sched_getaffinity(0), reason="needs cores 0 and 1 (a machine of two cores)")
def test_a_decomposed_solve_takes_the_same_path_on_one_core_and_on_two():
    one, two = solved("0"), solved("0,1")
    masters = [r for r in one["trace"] if r["phase"] == "milp"]
    assert max(r["master_nodes"] for r in masters) > 1, "no master branched: the case no longer tells the paths apart"
    assert one["work"]["highs_threads"] == two["work"]["highs_threads"]
    assert path(one) == path(two)
