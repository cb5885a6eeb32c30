"""Pure modules stay pure: the market's rules, the agent's model and the message schemas load neither the Zenoh
binding nor matplotlib, so they can be used, and tested, without a network or a display (docs/architecture.md)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PURE = ("dmo.market", "dmo.market.acflow", "dmo.market.acceptance", "dmo.market.distflow", "dmo.market.settlement",
        "microgrid_agent.model", "microgrid_agent.agent.bidding", "microgrid_agent.agent.machine", "messages",
        "messages.schemas")
HEAVY = ("zenoh", "matplotlib")

pytestmark = pytest.mark.slow  # only a fresh interpreter can say what an import loads


@pytest.mark.parametrize("module", PURE)
def test_a_pure_module_loads_neither_zenoh_nor_matplotlib(module):
    # A fresh interpreter: what this test process imported before says nothing about the module.
    code = (f"import sys, {module}\n"
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"importing {module} loads {out.stdout.strip()}"


def test_the_command_line_loads_no_feeder_machinery():
    """Every role starts through dmosim.cli, and the recorder and the agents never clear a feeder: scipy's LP (the
    feeder's clearing, about 40 MiB) and pandapower (its AC check, about 100 MiB) load only where a feeder is used."""
    code = ("import sys, dmosim.cli, dmosim.cli.record, messages.recording.recorder\n"
            "print(','.join(m for m in ('dmo.market.distflow', 'pandapower') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"starting the command line loads {out.stdout.strip()}"


def test_the_plotting_modules_leave_the_users_matplotlib_backend_alone():
    """A notebook user who imports our figures keeps the backend they chose: the modules draw through Agg canvases
    of their own (dmosim.results.style.figure), never through pyplot's backend, and still write PNGs."""
    code = ("import io, matplotlib\n"
            "matplotlib.use('svg')\n"
            "import dmosim.results.figures, dmosim.results.sweeps, dmosim.studies.figures, dmosim.cli.plot\n"
            "print(matplotlib.get_backend(), flush=True)\n"
            "from dmosim.results.style import figure\n"
            "fig = figure(figsize=(2, 1))\n"
            "fig.subplots().plot([0, 1])\n"
            "png = io.BytesIO()\n"
            "fig.savefig(png, format='png')\n"
            "print(png.getvalue()[:8] == b'\\x89PNG\\r\\n\\x1a\\n')")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.stdout.split()[:1] == ["svg"], "importing the plotting modules switched matplotlib's backend"
    assert out.returncode == 0 and out.stdout.split() == ["svg", "True"], out.stderr
