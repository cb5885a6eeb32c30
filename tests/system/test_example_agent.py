"""The third-party agent of examples/agent.py, written from docs/protocol.md with only zenoh and the standard
library, takes part in a real run of two market days beside a dmosim agent and is settled each day as its own
reports say, to the cent."""

from __future__ import annotations

import ast
import json
import subprocess
import sys

from test_market_day import DAY, DEADLINES, ENV, ROOT, TINY, dmosim

from dmosim.launch.processes import Roles, free_port, wait_listening
from messages import new_run_id
from messages.transport.credentials import create_auth_dir

EXAMPLE = ROOT / "examples" / "agent.py"


def test_the_example_imports_nothing_of_dmosim():
    tree = ast.parse(EXAMPLE.read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert "zenoh" in imported
    assert imported - {"zenoh"} <= set(sys.stdlib_module_names), imported


def test_the_example_agent_is_settled_as_its_own_reports_say(tmp_path):
    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    auth = create_auth_dir(tmp_path / "auth", run_id, ["mg1", "mg2"], dmo_client=False)
    result = tmp_path / "result.json"
    common = ["--run-id", run_id, "--market-day", DAY]
    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", "2", "--subperiods", "2",
                                  "--days", "2", "--auth-dir", str(auth), "--result", str(result), *DEADLINES),
                    log=tmp_path / "dmo.log", env=ENV)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        roles.start("mg1", dmosim("agent", *common, "--id", "mg1", "--connect", endpoint, "--auth-dir", str(auth),
                                  *TINY), log=tmp_path / "mg1.log", env=ENV)
        example = subprocess.run([sys.executable, str(EXAMPLE), "--id", "mg2", "--run-id", run_id, "--connect",
                                  endpoint, "--auth-dir", str(auth), "--timeout", "300"],
                                 capture_output=True, text=True, timeout=900, env=ENV)
        assert example.returncode == 0, example.stderr[-3000:]
        assert roles.roles["dmo"].process.wait(timeout=120) == 0, (tmp_path / "dmo.log").read_text()[-3000:]
    said = [json.loads(line) for line in example.stdout.strip().splitlines() if line.startswith("{")]
    run = json.loads(result.read_text())
    assert [s["market_day"] for s in said] == [d["market_day"] for d in run["days"]] and len(said) == 2
    for own, day in zip(said, run["days"]):
        assert own["meter_reports"] == 24
        assert own["statement_total"] == own["own_total"]  # to the cent: both are whole cents
        mine = day["settlement"]["mg2"]
        assert mine["total"] == own["own_total"] and mine["missing_subperiods"] == 0
        assert mine["deviation_penalty"] == 0 and mine["award_mwh"] > 0
    assert run["rejected_messages"] == 0, run["incidents"]
    assert not [i for i in run["incidents"] if i["agent"] == "mg2"], run["incidents"]
