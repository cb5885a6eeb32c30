"""A feeder file is data (docs/network.md, "A pandapower net as a feeder"; docs/security.md): a pandapower JSON whose
objects name a module of their own is refused in one line and nothing is imported, whether a user names it
(``run --feeder``) or a recording's experiment does; and a feeder file that only a recording names is not read at
all unless the user names it or trusts the recording (``--trust-rules``), like its code.

Each verb runs as a real process in a directory holding the module the file names, which writes a marker when
imported: with ``python -m dmosim``, which puts that directory on ``sys.path``, and with ``python -P -m dmosim`` (as
the installed ``dmosim`` command runs: no directory of the user's on ``sys.path``), whose file names the standard
library's ``this``, which prints the Zen of Python when imported. The recordings are crafted by the helper of the
rules' and strategies' test from a day's real messages.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_trust_recordings import ENV, MARKER, craft

from dmosim.launch.processes import free_port

ZEN = "The Zen of Python"
EVIL = f'from pathlib import Path\n\nPath("{MARKER}").write_text(__name__)\n'
# How each feeder file is run: the launcher, and the module its JSON names.
LAUNCHERS = {"evil": ([sys.executable, "-m", "dmosim"], "evil_module"),
             "zen": ([sys.executable, "-P", "-m", "dmosim"], "this")}


def crafted_net(module: str) -> str:
    """A pandapower JSON whose net names ``module``: what pandapower's reader would import before checking it."""
    return json.dumps({"_module": module, "_class": "pandapowerNet", "_object": {
        "bus": {"_module": "pandas.core.frame", "_class": "DataFrame", "orient": "split",
                "_object": json.dumps({"columns": ["vn_kv", "in_service"], "index": [0, 1],
                                       "data": [[12.47, True], [12.47, True]]})}}})


@pytest.fixture(scope="module")
def place(tmp_path_factory) -> Path:
    """The module, each feeder file, a recording naming each, and a run directory and a sweep of one of them."""
    root = tmp_path_factory.mktemp("feeders")
    (root / "evil_module.py").write_text(EVIL)
    for name, (_, module) in LAUNCHERS.items():
        (root / f"{name}.json").write_text(crafted_net(module))
        craft(root / f"{name}.mcap", None, f"{name}.json")
        run = root / f"{name}-sweep" / "001-run"
        run.mkdir(parents=True)
        craft(run / "recording.mcap", None, f"{name}.json")
    return root


def dmosim(place: Path, name: str, *args: str) -> subprocess.CompletedProcess:
    (place / MARKER).unlink(missing_ok=True)  # each verb on its own: the directory is the module's, for speed
    return subprocess.run([*LAUNCHERS[name][0], *args], capture_output=True, text=True, cwd=place, env=ENV,
                          timeout=120)


def nothing_imported(place: Path, out: subprocess.CompletedProcess) -> None:
    assert not (place / MARKER).exists(), (out.stdout[-500:], out.stderr[-2000:])
    assert ZEN not in out.stdout and ZEN not in out.stderr and "Traceback" not in out.stderr, out.stderr[-2000:]


def refused(out: subprocess.CompletedProcess, *words: str) -> None:
    """Exit 2, one line on stderr holding ``words``, nothing on stdout."""
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and not out.stdout, (out.stdout, out.stderr)
    assert all(w in out.stderr for w in words), out.stderr


@pytest.mark.parametrize("name", LAUNCHERS)
@pytest.mark.parametrize("args", [
    ("run", "--feeder", "{name}.json", "--check"),
    ("run", "--from", "{name}.mcap", "--check", "--trust-rules"),
    ("run", "--from", "{name}.mcap", "--check", "--feeder", "{name}.json"),
    ("run", "--from", "{name}-sweep/001-run", "--check", "--trust-rules"),
], ids=lambda a: " ".join(a) if isinstance(a, tuple) else a)
def test_a_feeder_file_naming_a_module_is_refused_in_one_line_and_nothing_is_imported(place, name, args):
    out = dmosim(place, name, *(a.format(name=name) for a in args))
    nothing_imported(place, out)
    refused(out, f"{name}.json", f"names _module '{LAUNCHERS[name][1]}'", "a feeder is data")


@pytest.mark.parametrize("name", LAUNCHERS)
@pytest.mark.parametrize("source", ["{name}.mcap", "{name}-sweep/001-run"])
def test_a_feeder_file_only_a_recording_names_is_not_read_unless_trusted(place, name, source):
    out = dmosim(place, name, "run", "--from", source.format(name=name), "--check")
    nothing_imported(place, out)
    refused(out, f"names the feeder file {name}.json", f"--feeder {name}.json", "--trust-rules", "docs/network.md")
    assert "_module" not in out.stderr  # not read at all


@pytest.mark.parametrize("name", LAUNCHERS)
@pytest.mark.parametrize("args", [
    ("info", "{name}.mcap"), ("cat", "{name}.mcap"), ("export", "{name}.mcap", "--out", "tables-{name}"),
    ("plot", "{name}.mcap", "--out", "{name}.png"), ("settle", "{name}.mcap"), ("settle", "{name}-sweep"),
    ("settle", "{name}.mcap", "--trust-rules"),
    ("replay", "{name}.mcap", "--rate", "max", "--wait-for-subscriber", "0", "--listen", "tcp/127.0.0.1:{port}"),
    ("replay", "{name}.mcap", "--as-dmo", "--trust-rules", "--timeout", "0.2", "--insecure", "--quiet", "--listen",
     "tcp/127.0.0.1:{port}"),
], ids=lambda a: " ".join(a[:3]) if isinstance(a, tuple) else a)
def test_no_verb_that_reads_a_recording_reads_the_feeder_file_it_names(place, name, args):
    out = dmosim(place, name, *(a.format(name=name, port=free_port()) for a in args))
    nothing_imported(place, out)
    # each does what it does without the feeder: a recorded day's own messages are all it reads (replay --as-dmo
    # waits for an agent that never comes, a runtime failure after it has read the recording)
    assert out.returncode == (1 if "--as-dmo" in args else 0), out.stderr[-2000:]
