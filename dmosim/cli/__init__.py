"""The ``dmosim`` command line: one module per verb (its flags and its body), the flags several verbs share
(flags.py) and what every verb prints through (console.py); main.py joins them."""

from ..console import refuse_shadowed_packages

refuse_shadowed_packages()  # before main.py imports them: a user's scenarios.py must not pass for ours

from .main import build_parser, console, main, native_stdout_to_stderr  # noqa: E402

__all__ = ["build_parser", "console", "main", "native_stdout_to_stderr"]
