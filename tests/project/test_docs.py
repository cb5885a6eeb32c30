"""The documentation is a contract: what it names in the code exists, docs/model.md maps each equation to the
functions that build it, the README lists every verb, and nothing cites a document the repository does not hold."""

from __future__ import annotations

import argparse
import importlib
import inspect
import re
from pathlib import Path

import pytest

from dmosim.cli.main import VERBS, build_parser
from messages.reference import BEGIN, END, reference

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
NOTES = sorted((ROOT / "docs" / "notes").glob("*.md"))
PACKAGES = ("scenarios", "messages", "microgrid_agent", "dmo", "dmosim", "tests", "examples")
CODE = [p for package in PACKAGES[:5] for p in sorted((ROOT / package).rglob("*.py"))]


def text(path: Path) -> str:
    return path.read_text()


@pytest.mark.parametrize("doc", DOCS + NOTES, ids=lambda p: p.name)
def test_every_path_a_document_names_exists(doc):
    # dmosim/RUN/... is a key expression of the wire (docs/protocol.md), not a path: paths are lower case
    named = set(re.findall(r"\b((?:%s)/(?![A-Z])[\w/]*\w(?:\.py|\.toml|/(?=[`\s,.;)])))" % "|".join(PACKAGES), text(doc)))
    for braces in re.findall(r"\b((?:%s)/[\w/]*)\{([\w,]+)\}\.py" % "|".join(PACKAGES), text(doc)):
        named |= {f"{braces[0]}{name}.py" for name in braces[1].split(",")}
    missing = sorted(p for p in named if not (ROOT / p).exists() and "{" not in p)
    assert not missing, f"{doc.name} names {missing}"


@pytest.mark.parametrize("doc", DOCS + NOTES, ids=lambda p: p.name)
def test_every_dotted_name_a_document_gives_resolves(doc):
    wrong = []
    # a name the code writes as a string (an MCAP schema or metadata name such as dmosim.any) is not an import
    literals = {m for path in CODE for m in re.findall(r"[\"']((?:dmosim|dmo)\.\w+)[\"']", text(path))}
    for name in sorted(set(re.findall(r"`((?:scenarios|messages|microgrid_agent|dmosim|dmo)(?:\.\w+)+)`", text(doc)))
                       - literals):
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):  # the longest importable module, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = getattr(obj, attr)
            except AttributeError:
                wrong.append(name)
            break
        else:
            wrong.append(name)
    assert not wrong, f"{doc.name} names {wrong}"


@pytest.mark.parametrize("note", NOTES, ids=lambda p: p.name)
def test_every_note_gives_its_date_command_and_decision_and_a_user_document_links_it(note):
    """docs/notes/ is the design log: each file one decision, dated, with the command that measured it, and reached
    from the user documents, which keep only the reference."""
    head = text(note).split("\n\n", 2)[1]
    assert re.search(r"^- \*\*Date:\*\* \d{4}-\d{2}-\d{2}", head, re.M), note.name
    assert "- **Measured with:** " in head and "- **Decision:** " in head, note.name
    assert any(note.name in text(doc) for doc in DOCS), f"no user document links {note.name}"


def test_model_md_maps_each_equation_to_functions_that_build_it():
    import microgrid_agent.model as model  # noqa: PLC0415

    table = text(ROOT / "docs" / "model.md").split("## Equation by equation", 1)[1].split("\n## ", 1)[0]
    rows = [r for r in table.splitlines() if re.match(r"\| \(\d+\)", r)]
    covered = set()
    modules = [importlib.import_module(f"microgrid_agent.model.{p.stem}")
               for p in sorted((ROOT / "microgrid_agent" / "model").glob("*.py")) if p.stem != "__init__"]
    for row in rows:
        label, functions = row.split("|")[1:3]
        first, last = (int(n) for n in re.match(r"\s*\((\d+)\)(?:-\((\d+)\))?", label).groups(default="0"))
        equations = range(first, max(first, last) + 1)
        names = re.findall(r"`(\w+)`", functions)
        assert names, row
        sources = []
        for name in names:
            found = [getattr(m, name) for m in modules if inspect.isfunction(getattr(m, name, None))
                     and getattr(m, name).__module__ == m.__name__]
            assert found, f"docs/model.md: {name} is not a function of microgrid_agent/model/"
            sources.append(inspect.getsource(found[0]))
        for n in equations:
            assert any(f"({n})" in s for s in sources), f"docs/model.md: none of {names} builds ({n})"
            covered.add(n)
    assert covered == set(range(1, 22)), f"equations without a row: {sorted(set(range(1, 22)) - covered)}"
    assert model.build  # the table maps the package the solvers build from


def test_the_route_auto_takes_reads_the_same_in_the_docs_as_in_the_code():
    from microgrid_agent.solvers.routes import auto_rule  # noqa: PLC0415

    method = next(a for _, a in flags_of(verb_parser("solve"), "solve") if "--method" in a.option_strings)
    assert auto_rule() in text(ROOT / "docs" / "solver.md") and auto_rule() in " ".join(method.help.split())


def flags_of(parser: argparse.ArgumentParser, prog: str):
    """(where, action) of every argument of ``parser`` and of its sub-verbs (``bench solver``...)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from flags_of(sub, f"{prog} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield prog, action


def verb_parser(name: str) -> argparse.ArgumentParser:
    parser = build_parser(name)
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]


def test_every_flag_of_every_verb_is_documented():
    """The README's table is one line per verb; each flag is explained in the document that verb points to, or
    another: every option of every verb (and of ``bench``'s sub-verbs) is named somewhere in docs/ or the README."""
    written = "\n".join(text(doc) for doc in DOCS)
    missing = [f"{prog} {flag}" for name in VERBS for prog, action in flags_of(verb_parser(name), name)
               for flag in action.option_strings
               if flag.startswith("--") and not re.search(re.escape(flag) + r"(?![\w-])", written)]
    assert not missing, missing


def test_readme_lists_every_verb():
    readme = text(ROOT / "README.md")
    missing = [verb for verb in VERBS if f"`dmosim {verb}" not in readme]
    assert not missing, missing


@pytest.mark.parametrize("path", DOCS + CODE, ids=lambda p: str(p.relative_to(ROOT)))
def test_nothing_cites_the_specification(path):
    """Help texts, code and docs point to the repository's own documents; the product specification is not one."""
    assert not re.search(r"\bSPEC section|\bSPEC\.md|\bSPEC \d", text(path)), path


def test_protocol_md_holds_the_message_reference_the_types_generate():
    doc = text(ROOT / "docs" / "protocol.md")
    held = doc[doc.index(BEGIN):doc.index(END) + len(END)]
    assert held == reference(), ("docs/protocol.md's message reference differs from messages/schemas.py: "
                                 "paste the output of `dmosim schemas --markdown` between its markers")


def test_protocol_md_key_table_has_a_row_for_every_route_of_the_code():
    """docs/protocol.md's table of key expressions lists each key a message travels on (messages.keys.ROUTES) with
    the type it carries, and no key the code does not route."""
    from messages.keys import ROUTES  # noqa: PLC0415
    from messages.schemas import MODELS  # noqa: PLC0415

    doc = text(ROOT / "docs" / "protocol.md").split("## Key expressions", 1)[1].split("```", 2)[1]
    rows = {parts[0]: parts[1] for parts in (line.split() for line in doc.splitlines())
            if parts and parts[0].startswith("dmosim/<run>/") and not parts[0].startswith(("dmosim/<run>/alive/",
                                                                                          "dmosim/<run>/link/"))}
    expected = {}
    for kind, (role, topic, named) in ROUTES.items():
        key = (f"dmosim/<run>/agent/<agent>/{topic}" if role == "agent" else
               f"dmosim/<run>/dmo/{topic}" + ("/<agent>" if named else ""))
        expected[key] = MODELS[kind].__name__
    assert rows == expected


def test_docs_recording_md_gives_the_path_a_run_records_to():
    """Where docs/recording.md says where `dmosim run` records by default, it names the run directory's recording."""
    from dmosim.experiment.rundir import RUNS, RunDir  # noqa: PLC0415

    section = text(ROOT / "docs" / "recording.md").split("## `dmosim run` and `dmosim record`", 1)[1]
    said = " ".join(section.split("`dmosim run` records by default to", 1)[1].split(")", 1)[0].split())
    assert f"`{RunDir(RUNS / '<run_id>').recording.as_posix()}`" in said, said


def test_every_protocol_version_the_docs_give_is_the_codes():
    """Wherever a document says which protocol version is current, it says the one the code speaks."""
    from messages.schemas import SCHEMA_VERSION  # noqa: PLC0415

    said = [(doc.name, int(n)) for doc in DOCS for n in re.findall(r"\bcurrently (\d+)\b", text(doc))]
    assert ("protocol.md", SCHEMA_VERSION) in said
    assert all(n == SCHEMA_VERSION for _, n in said), said


def test_ci_runs_the_readmes_test_command():
    """README.md opens with two commands; the second is the test command, and .ci/run runs exactly it."""
    commands = text(ROOT / "README.md").split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert len(commands) == 2 and "pytest" in commands[1]
    assert commands[1] in text(ROOT / ".ci" / "run").splitlines()
