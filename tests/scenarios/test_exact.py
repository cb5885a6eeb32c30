"""Sums that give the same bits on every CPU (scenarios/exact.py), and what rests on them: a decomposition's path and
a feeder's clearing, each run in two processes forced onto different BLAS kernels."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from scenarios import exact


def test_the_sums_are_those_of_numpy_correctly_rounded():
    rng = np.random.default_rng(0)
    a, x = rng.normal(size=(5, 7)), rng.normal(size=7)
    assert exact.matvec(a, x) == pytest.approx(a @ x, abs=1e-14)
    assert exact.matvec(a, x)[2] == math.fsum(a[2] * x)  # one rounding, of the exact sum
    assert exact.matvec(np.zeros((0, 3)), np.ones(3)).shape == (0,)
    assert exact.dot(np.array([1e16, 1.0, -1e16]), np.ones(3)) == 1.0  # added left to right: 0.0
    weight, data = rng.random((2, 5)), rng.normal(size=(3, 5, 4))
    assert exact.weighted(weight, data, 1) == pytest.approx(np.einsum("gs,rsh->rgh", weight, data), abs=1e-14)
    assert exact.weighted(weight, data[0], 0) == pytest.approx(weight @ data[0], abs=1e-14)
    mask, p = (rng.random((4, 6)) < 0.5).astype(float), rng.normal(size=(3, 6))
    assert exact.masked_sums(mask, p) == pytest.approx(p @ mask.T, abs=1e-14)
    assert exact.masked_sums(mask, p[0]).shape == (4,)


_PROBE = """
import json, sys
import numpy as np
rng = np.random.default_rng(0)
probe = (rng.normal(size=(100, 400)) @ rng.normal(size=400)).tobytes().hex()  # BLAS as numpy calls it here
"""

_SEARCH = _PROBE + """
from microgrid_agent.instance import make_instance
from microgrid_agent.solvers.benders import solve_decomposed
from scenarios.case import load_case
inst = make_instance(load_case("paper"), scenarios=5, subperiods=1, seed=0)
s = solve_decomposed(inst.case, inst.scen, inst.params, gap=0.005, workers=1)
bits = [[float(r["lower_bound"]).hex(), float(r["upper_bound"]).hex()] for r in s.extra["trace"]]
print(json.dumps({"probe": probe, "result": [bits, s.objective.hex()]}))
"""

_CLEARING = _PROBE + """
from dmo.market.clearing import BidCurve, Step
from dmo.market.distflow import clear_network
from scenarios.horizon import HOURS
from scenarios.network import load_network
net = load_network("ieee33", load_scale=1.6)
names = [f"mg{i}" for i in range(12)]
buses = {n: int(b) for n, b in zip(names, rng.choice(np.arange(1, net.n_buses), 12, replace=False))}
bids = [BidCurve(n, tuple(tuple(Step(float(p), float(q)) for p, q in zip(np.sort(rng.uniform(20, 200, 3))[::-1],
                                                                        rng.uniform(-1.5, 1.5, 3)))
                          for _ in range(HOURS))) for n in names]
bits = {}
for method in ("lindistflow", "ac"):
    r = clear_network(bids, net, buses, 60.0, 3.0, 3.0, agents=names, method=method)
    bits[method] = {k: np.asarray(v).tobytes().hex() for k, v in vars(r).items() if isinstance(v, np.ndarray)}
    bits[method]["awards"] = {a: np.asarray(v).tobytes().hex() for a, v in r.awards.items()}
print(json.dumps({"probe": probe, "result": bits}))
"""


def _numpy_dispatch() -> str:
    """numpy's own vector code above its baseline (AVX2, AVX-512, ... on x86-64), to be turned off."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__  # noqa: PLC0415  (numpy 2)
    except ImportError:
        return ""
    return " ".join(__cpu_dispatch__)


def under_two_kernels(code: str) -> list:
    """What ``code`` prints as its result in a process on OpenBLAS's AVX2 kernels and numpy's best vector code, and
    in one on OpenBLAS's SSE3 kernels (both in every x86-64 DYNAMIC_ARCH build) and numpy's baseline code; skipped
    where numpy's BLAS adds in one order whatever is asked."""
    runs = []
    for env in ({"OPENBLAS_CORETYPE": "Haswell"},
                {"OPENBLAS_CORETYPE": "Prescott", "NPY_DISABLE_CPU_FEATURES": _numpy_dispatch()}):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True,
                              env=os.environ | env)
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))  # HiGHS's banner may come first
    if runs[0]["probe"] == runs[1]["probe"]:
        pytest.skip("this numpy's BLAS adds in one order on this machine whatever kernel is asked for")
    return [run["result"] for run in runs]


@pytest.mark.slow  # each kernel is chosen as numpy loads: a process apiece
def test_the_search_takes_the_same_path_whichever_blas_kernels_the_cpu_gets():
    """Cut right-hand sides and upper bounds summed by BLAS moved a decomposition's path from one CPU to another
    (docs/solver.md): every bound, bit for bit, and the schedule's cost must be the same."""
    avx2, sse3 = under_two_kernels(_SEARCH)
    assert avx2 == sse3


@pytest.mark.slow  # each kernel is chosen as numpy loads: a process apiece
def test_a_feeder_clears_to_the_same_bits_whichever_blas_kernels_the_cpu_gets():
    """Awards, prices, flows and voltages of a day on the IEEE 33-bus feeder, cleared on LinDistFlow and AC-faithful:
    an award's last bit is an agent's schedule's data, so it must not depend on the CPU."""
    avx2, sse3 = under_two_kernels(_CLEARING)
    assert avx2 == sse3
