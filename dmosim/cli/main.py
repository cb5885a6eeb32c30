"""The ``dmosim`` command line: parses flags, runs one verb, maps bad input to exit 2 and failures to exit 1.

Each verb is a module of this package with ``HELP``, ``add_arguments(parser)`` and ``run(args)``, as the verbs of
``ros2 bag`` and the mcap CLI are; only the chosen verb's flags are built, so the command line starts fast.
"""

from __future__ import annotations

import argparse
import os
import sys

from messages.transport.heap import limit_arenas
from scenarios.case import CaseError

from ..console import UsageError, last_words
from . import (agent, bench, cat, credentials, dmo, export, fleet, info, plot, record, replay, router, run, schemas,
               settle, solve, study, sweep, view)

DESCRIPTION = ("A distribution market operator and its microgrid agents as processes over Zenoh: run market days, "
               "solve a microgrid's stochastic schedule, record, replay and re-settle days (README.md).")
EXIT_USAGE = 2
EXIT_FAILURE = 1

# In the order `dmosim --help` lists them: the whole day, its roles, the scheduling model, recordings, benchmarks.
VERBS = {"run": run, "sweep": sweep, "fleet": fleet, "dmo": dmo, "agent": agent, "record": record, "router": router,
         "credentials": credentials, "solve": solve, "study": study, "info": info, "replay": replay, "settle": settle, "cat": cat,
         "export": export, "plot": plot, "schemas": schemas, "view": view, "bench": bench}


class _Version(argparse.Action):
    """``dmosim --version``: this package's version and the protocol's, the two a bug report needs."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, help="print the version of dmosim and its protocol, and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        from messages import SCHEMA_VERSION  # noqa: PLC0415  (only when asked)
        from messages.recording.layout import versions  # noqa: PLC0415

        v = versions()
        print(f"dmosim {v['dmosim']} (message schemas v{SCHEMA_VERSION}; Python {v['python']}, eclipse-zenoh "
              f"{v['eclipse-zenoh']}, highspy {v['highspy']})")
        parser.exit()


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would print the whole usage; one line is enough
        raise UsageError(f"{self.prog}: {message}")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every verb, with the flags of ``command`` only (none if None: ``dmosim --help`` lists the
    verbs; ``dmosim VERB --help`` shows the verb's flags)."""
    parser = _Parser(prog="dmosim", description=DESCRIPTION)
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, verb in VERBS.items():
        p = sub.add_parser(name, help=verb.HELP, description=verb.HELP)
        if name == command:
            verb.add_arguments(p)
        p.set_defaults(verb=verb)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        argv = sys.argv[1:] if argv is None else argv
        args = build_parser(argv[0] if argv and not argv[0].startswith("-") else None).parse_args(argv)
        code = args.verb.run(args) or 0
        sys.stdout.flush()  # out before the exit: a reader that stalls it is met here, where Ctrl-C ends it with 130
        return code
    except (UsageError, CaseError) as exc:  # one line, even where a path or a key the user gave holds a newline
        print("error: " + str(exc).replace("\n", "\\n"), file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        last_words("interrupted")  # never waits for a reader of its output: whoever reads it, it exits now
        return 130
    except BrokenPipeError:  # the reader of stdout went away (dmosim info ... | head): nothing left to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as exc:  # a runtime failure: one line, unless DMOSIM_DEBUG asks for the traceback
        if os.environ.get("DMOSIM_DEBUG"):
            raise
        detail = str(exc) if isinstance(exc, RuntimeError) else f"{type(exc).__name__}: {exc}"
        print(f"failed: {detail}", file=sys.stderr)
        return EXIT_FAILURE


def native_stdout_to_stderr() -> None:
    """Keep stdout for what dmosim prints (``--json`` output is parsed by other programs): native libraries that
    write to file descriptor 1 behind Python's back, such as HiGHS 1.16, which prints its banner whenever a
    solver object is created and before any option can silence it, go to stderr instead. Forked workers and
    child processes inherit the same arrangement."""
    sys.stdout.flush()
    stdout = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = open(stdout, "w", buffering=1, encoding=sys.stdout.encoding, errors=sys.stdout.errors)


def console() -> int:
    """The ``dmosim`` executable: ``main`` with stdout reserved for dmosim's own output, and few C heap arenas
    (``limit_arenas``: a role lives for days)."""
    limit_arenas()
    native_stdout_to_stderr()
    return main()
