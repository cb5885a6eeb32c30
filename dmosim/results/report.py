"""The result of a run as ``dmosim run`` writes it (``result.json``, ``--json``): the DMO's part (``DmoReport``) with
what the launcher adds, typed (docs/experiments.md, "The result"), and read back from a file or a command's output
with one line saying what is wrong."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError

from dmo.operator.report import DmoReport, ResultModel

from ..console import UsageError

RESULT_SCHEMA = "result.schema.json"  # the file name of result_schema(), beside the messages' schemas


class Memory(ResultModel):
    """A role's memory as sampled, MiB."""

    rss_mib: float = Field(description="resident now")
    peak_mib: float = Field(description="peak so far")
    pss_mib: float | None = Field(description="its proportional share now; null where the kernel has no smaps_rollup")


class Resettled(ResultModel):
    """The settled days re-settled from the recording alone, as ``dmosim settle`` does."""

    identical: bool
    differences: list[str] | None = Field(None, description="one line each, after the market day")
    error: str | None = Field(None, description="what kept a day from being re-settled")


class Recorded(ResultModel):
    """What the recording holds."""

    messages: int | None = Field(None, description="absent when the recording cannot be read")
    channels: int | None = None
    bytes: int | None = None
    error: str | None = Field(None, description="why the recording cannot be read")
    complete: bool = Field(description="the file whole and the recorder never failed")
    recorder: str | None = Field(description="how the recorder failed, or null")
    tables_from: Literal["recording", "journal"] | None = Field(None, description=(
        "where the tables came from: the journal when the recording is incomplete"))
    resettled: Resettled | None = Field(None, description="when the recording is complete")


class Reproduced(ResultModel):
    """With ``--from``: whether the run settled every agent as the recording it repeats."""

    source: str
    identical: bool
    differences: list[str] = Field(description="one line per agent, day and hour")
    error: str | None = Field(None, description="what kept the source from being read")


class Routers(ResultModel):
    """With ``--routers N``: where each router listens, and which router each role connected to."""

    endpoints: dict[str, str]
    roles: dict[str, str]


class Placement(ResultModel):
    """With ``--cluster``: the scheduler, the DMO's endpoint, and which agents each worker ran."""

    scheduler: str
    dmo: str
    agents: dict[str, list[str]]


class Verdict(ResultModel):
    """Whether the run's results can be trusted (dmosim/results/verdict.py)."""

    ok: bool
    problems: list[str] = Field(description="one line each, in the verdict's order")


class RunReport(DmoReport):
    """The result of ``dmosim run``: the DMO's (``DmoReport``) with what the launcher adds."""

    wall_s: float = Field(description="seconds from start to the last role's exit")
    memory_mib: dict[str, dict[str, Memory]] | None = Field(None, description=(
        "day -> role -> its memory as the day's last hour starts (not in one process)"))
    experiment: str = Field(description="the experiment's name")
    run_dir: str
    logs: str
    recording: str | None = Field(description="the recording, null with --no-record")
    faults: list[str] = Field(description="the injected faults")
    restarts: dict[str, int] = Field(description="processes restarted, name -> count")
    routers: Routers | None = None
    cluster: Placement | None = None
    recorded: Recorded | None = Field(None, description="absent with --no-record")
    reproduced: Reproduced | None = Field(None, description="with --from")
    tables: dict[str, str] | None = Field(None, description="table -> its file")
    figure: str | None = None
    verdict: Verdict


def result_schema() -> dict:
    """The JSON Schema (draft 2020-12) of ``result.json`` as a reader takes it: a key whose field has a default may
    be absent (``dmosim schemas --out DIR`` writes it as ``RESULT_SCHEMA``; docs/result.schema.json holds it)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": "urn:dmosim:result",
            **RunReport.model_json_schema()}


def result_text(report: DmoReport) -> str:
    """A result as ``result.json`` holds it and ``--json`` prints it."""
    return json.dumps(report.model_dump(mode="json"), indent=2)


def parse_result(text: str, source: str, model: type[DmoReport] = RunReport) -> DmoReport:
    """A result read from ``text`` (from ``source``, as the error names it); ``UsageError``, one line naming the
    source and what is wrong, if it is not one."""
    try:
        return model.model_validate_json(text)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "the top"
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise UsageError(f"{source}: not a dmosim result: {where}: {first['msg']}{more}") from None


def read_result(path: str | Path, model: type[DmoReport] = RunReport) -> DmoReport:
    """``result.json`` at ``path`` read (``parse_result``); a file that cannot be read is one line too."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{path}: cannot read the result: {getattr(exc, 'strerror', None) or exc}") from None
    return parse_result(text, str(path), model)
