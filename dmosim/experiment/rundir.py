"""Where a run leaves what it made: one directory, ``./runs/<run_id>/`` unless the user names another.

    experiment.toml   the resolved experiment (every default filled in): `dmosim run experiment.toml` repeats it
    fleet.toml        the fleet the run generated (agents.generate), which experiment.toml names; its cases in cases/
    recording.mcap    every message of the run
    result.json       the DMO's result, as `dmosim run --json` prints it
    tables/*.csv      the recording as tidy tables (`dmosim export`)
    run.png           the run as a figure (`dmosim plot`)
    logs/             each role's log, the DMO's journal

The run's credentials are never in it (dmosim/launch/local.py keeps them in a private temporary directory).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

RUNS = Path("runs")


class RunDirError(ValueError):
    """A run directory that cannot be used; one line."""


@dataclass(frozen=True)
class RunDir:
    root: Path

    @property
    def experiment(self) -> Path:
        return self.root / "experiment.toml"

    @property
    def fleet(self) -> Path:
        return self.root / "fleet.toml"

    @property
    def recording(self) -> Path:
        return self.root / "recording.mcap"

    @property
    def result(self) -> Path:
        return self.root / "result.json"

    @property
    def tables(self) -> Path:
        return self.root / "tables"

    @property
    def figure(self) -> Path:
        return self.root / "run.png"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    @classmethod
    def make(cls, out: str | Path | None, run_id: str, overwrite: bool = False) -> RunDir:
        """The run directory ``out`` (default ``runs/<run_id>``), created; one that already holds a run is refused
        unless ``overwrite``."""
        root = claim_directory(Path(out) if out is not None else RUNS / run_id, overwrite)
        (root / "logs").mkdir(exist_ok=True)
        return cls(root)


def check_directory(root: Path, overwrite: bool = False) -> Path:
    """``root``, if a run or a sweep may write into it (``claim_directory`` would take it), else ``RunDirError``:
    what ``--check`` asks before anything is made."""
    if root.exists() and not root.is_dir():
        raise RunDirError(f"{root} exists and is not a directory")
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise RunDirError(f"{root} is not empty; choose another --out or pass --overwrite")
    return root


def claim_directory(root: Path, overwrite: bool = False) -> Path:
    """``root``, created if missing, for a run or a sweep to write into: one that holds anything already is
    refused unless ``overwrite``, so no earlier result is lost by mistake."""
    check_directory(root, overwrite)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunDirError(f"cannot create {root}: {exc.strerror or exc}") from None
    return root
