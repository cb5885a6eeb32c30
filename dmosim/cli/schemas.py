"""``dmosim schemas``: the JSON Schema of every message kind, one file each with an index, so that agents in other
languages can generate their types, and of a run's ``result.json``; or, with ``--markdown``, the protocol reference
of docs/protocol.md."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from messages.reference import reference, schema_files

from ..console import UsageError
from ..results.report import RESULT_SCHEMA, result_schema

HELP = "the JSON Schema of every message kind and of a run's result (and the protocol reference)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--out", metavar="DIR", help="write <kind>.schema.json for every kind, index.json and result.schema.json here")
    out.add_argument("--markdown", action="store_true", help="print the message reference of docs/protocol.md")


def run(args) -> int:
    if args.markdown:
        print(reference())
        return 0
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {args.out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {args.out}: cannot create the directory ({exc.strerror})") from None
    files = schema_files()
    for name, content in {**files, RESULT_SCHEMA: result_schema()}.items():
        (out / name).write_text(json.dumps(content, indent=2) + "\n")
    print(f"wrote {len(files) - 1} message schemas, index.json and {RESULT_SCHEMA} (a run's result.json) to {out}")
    return 0
