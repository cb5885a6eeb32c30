"""The ``dmosim`` command line: one module per verb (its flags and its body), the flags several verbs share
(flags.py) and what every verb prints through (console.py); main.py joins them."""

from .main import build_parser, console, main, native_stdout_to_stderr

__all__ = ["build_parser", "console", "main", "native_stdout_to_stderr"]
