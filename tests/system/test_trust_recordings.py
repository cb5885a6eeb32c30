"""A recording is data (docs/settlement.md, "Rules named by recordings"): a recording, run directory or sweep directory
whose awards, statements and experiment attachment name a settlement rule of their own never make dmosim import or
call it, from any verb that reads recordings, run in a directory that holds the rule's file. Naming the rule
yourself, or ``--trust-rules``, does load it, so the marker the rule's import writes shows the test can fail.

The recording is built with the recorder's writer from a day's real messages (no run, no solver); each verb runs as
a real process.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from dmosim.bench.recording import synthetic_day
from dmosim.launch.processes import free_port
from messages import decode, encode
from messages.keys import new_run_id
from messages.recording import RecordingWriter

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
DAY = "2026-07-01"
MARKER = "imported.txt"
# A rule of one's own that settles as the paper's rule at the day's rates, and says when its module was imported.
EVIL = f'''from pathlib import Path

Path("{MARKER}").write_text(__name__)

from dmo.market.rules import BUILT_IN


def rule(day, **params):
    return BUILT_IN["paper"](day, penalty=150.0, credit=0.0)
'''


def craft(path: Path, rule: str | None, feeder: str | None = None) -> Path:
    """A recorded day of one agent whose awards, statements and experiment.toml name ``rule`` (None: as recorded, the
    paper's rule), and whose experiment.toml names ``feeder`` (None: none)."""
    run_id = new_run_id()
    day = []
    for key, payload in synthetic_day(run_id, 1, 1, market_day=DAY):
        message = decode(payload)
        if rule is not None and hasattr(message, "settlement_rule"):
            payload = encode(message.model_copy(update={"settlement_rule": rule}))
        day.append((key, payload))
    experiment = (f'market_day = "{DAY}"\n\n[agents]\ncount = 1\n\n'
                  + (f'[market]\nsettlement = "{rule}"\n\n' if rule is not None else "")
                  + "[schedule]\nscenarios = 1\n" + (f'\n[network]\nfeeder = "{feeder}"\n' if feeder else "")).encode()
    with RecordingWriter(path, run_id) as writer:
        writer.start({"market_day": DAY, "agents": "mg1"}, [("experiment.toml", "application/toml", experiment)])
        for i, (key, payload) in enumerate(day):
            writer.write(key, payload, 1_700_000_000_000_000_000 + i)
    return path


@pytest.fixture
def place(tmp_path) -> Path:
    """A directory holding the rule's file (as evil.py and as the module evil_module), a crafted recording of each
    name, a run directory and a sweep directory: the verbs run here, where a relative name would find the rule."""
    (tmp_path / "evil.py").write_text(EVIL)
    (tmp_path / "evil_module.py").write_text(EVIL)
    craft(tmp_path / "file.mcap", "evil.py:rule")
    craft(tmp_path / "module.mcap", "evil_module:rule")
    run = tmp_path / "sweep" / "001-run"
    run.mkdir(parents=True)
    craft(run / "recording.mcap", "evil.py:rule")
    (run / "experiment.toml").write_text('[market]\nsettlement = "evil.py:rule"\n')
    return tmp_path


def dmosim(place: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dmosim", *args], capture_output=True, text=True, cwd=place,
                          env=ENV, timeout=timeout)


def refused(out: subprocess.CompletedProcess, rule: str) -> str:
    """Exit 2 with one line that names the rule and the flag that would trust it."""
    assert out.returncode == 2, (out.returncode, out.stdout[-500:], out.stderr[-2000:])
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr, out.stderr
    assert rule in out.stderr and "--trust-rules" in out.stderr, out.stderr
    return out.stderr


def test_no_verb_imports_a_rule_that_a_recording_names(place):
    rule = "evil.py:rule"
    shown = {"info": dmosim(place, "info", "file.mcap"), "cat": dmosim(place, "cat", "file.mcap"),
             "export": dmosim(place, "export", "file.mcap", "--out", "tables"),
             "plot": dmosim(place, "plot", "file.mcap", "--out", "day.png"),
             "replay": dmosim(place, "replay", "file.mcap", "--rate", "max", "--wait-for-subscriber", "0",
                              "--listen", f"tcp/127.0.0.1:{free_port()}"),
             # comparing other rules needs the recorded one only for an agent with no recorded statement
             "settle --rule": dmosim(place, "settle", "file.mcap", "--penalty", "0", "--rule", "paper")}
    for verb, out in shown.items():
        assert out.returncode == 0, (verb, out.stderr[-2000:])
    assert re.search(rf"^settled by: .*{re.escape(rule)}$", shown["info"].stdout, re.M), shown["info"].stdout
    assert f'"settlement_rule":"{rule}"' in shown["cat"].stdout.replace(" ", "")
    for args in (["settle", "file.mcap"], ["settle", "sweep/001-run"], ["settle", "sweep"],
                 ["replay", "file.mcap", "--as-dmo", "--insecure", "--listen", f"tcp/127.0.0.1:{free_port()}"],
                 ["run", "--from", "file.mcap", "--check"], ["run", "--from", "sweep/001-run", "--check"],
                 ["run", "--from", "file.mcap", "--out", "again", "--quiet"]):
        err = refused(dmosim(place, *args), rule)
        if args[0] == "run":
            assert "--settlement evil.py:rule" in err, err  # the other way to run it: name it
    assert not (place / MARKER).exists() and not (place / "again").exists()
    # the module form too
    for args in (["settle", "module.mcap"], ["run", "--from", "module.mcap", "--check"],
                 ["replay", "module.mcap", "--as-dmo", "--insecure", "--listen", f"tcp/127.0.0.1:{free_port()}"]):
        refused(dmosim(place, *args), "evil_module:rule")
    assert not (place / MARKER).exists()


@pytest.mark.parametrize("args, code", [
    (["settle", "file.mcap", "--trust-rules"], 0),
    (["settle", "sweep", "--trust-rules"], 0),
    (["settle", "file.mcap", "--rule", "./evil.py:rule"], 0),   # the same code, named another way
    (["run", "--from", "file.mcap", "--check", "--trust-rules"], 0),
    (["run", "--from", "file.mcap", "--check", "--settlement", "evil.py:rule"], 0),
    (["settle", "module.mcap", "--trust-rules"], 0),
])
def test_naming_the_rule_or_trusting_the_recording_loads_it(place, args, code):
    out = dmosim(place, *args)
    assert out.returncode == code, out.stderr[-2000:]
    assert (place / MARKER).exists()


def test_replay_as_dmo_trusted_loads_the_rule_before_it_waits_for_an_agent(place):
    out = dmosim(place, "replay", "file.mcap", "--as-dmo", "--trust-rules", "--timeout", "0.2", "--insecure",
                 "--listen", f"tcp/127.0.0.1:{free_port()}", "--quiet")
    assert (place / MARKER).read_text().startswith("dmosim_rule_")  # imported from the file, as a rule
    assert out.returncode == 1 and "did not register" in out.stderr  # nobody came: a runtime failure, after it


def test_the_trust_flag_goes_only_where_a_recording_is_read(place):
    for args in (["run", "--check", "--trust-rules"], ["replay", "file.mcap", "--trust-rules"]):
        out = dmosim(place, *args)
        assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
        assert re.search(r"--trust-rules goe?s? with --(from|as-dmo)", out.stderr), out.stderr
