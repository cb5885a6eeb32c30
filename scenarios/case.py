"""Load, validate and write a microgrid case file (TOML): the data of the paper's Section IV as typed, immutable
objects."""

from __future__ import annotations

import stat
import sys
import tomllib
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from scenarios.horizon import HOURS
from scenarios.tomltext import toml_text

DATA_DIR = Path(__file__).parent / "data"
# Bounds of every TOML file dmosim reads (case, fleet, experiment, a sweep's --set values). The largest we ship,
# paper.toml, is 9.5 kB and a fleet of 1,024 members about 100 kB: 1 MiB is ten times that and parses in well
# under a second. The deepest nesting a valid file needs is 4 (a case's units -> unit -> provenance -> note).
MAX_TOML_BYTES = 1 << 20
MAX_TOML_DEPTH = 8

NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Hour = Annotated[int, Field(ge=1, le=HOURS)]
Duration = Annotated[int, Field(ge=1, le=HOURS)]
Profile = Annotated[list[NonNeg], Field(min_length=HOURS, max_length=HOURS)]
SignedProfile = Annotated[list[Annotated[float, Field(allow_inf_nan=False)]], Field(min_length=HOURS, max_length=HOURS)]


class CaseError(ValueError):
    """A case file that cannot be used; the message names the file and the field."""


class _CaseModel(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Unit(_CaseModel):
    """A dispatchable unit i in G: limits of (3), ramps of (4)-(5), minimum up/down times of (6)-(7), cost F."""

    name: str
    cost: NonNeg
    p_min: NonNeg
    p_max: Pos
    min_up: Duration
    min_down: Duration
    ramp_up: Pos
    ramp_down: Pos
    startup_cost: NonNeg = 0.0
    shutdown_cost: NonNeg = 0.0
    initial_on: bool = False
    p_initial: NonNeg | None = None
    # Hours the unit has been in its initial state at midnight (the day before ended so); None: long enough for
    # its minimum up and down times. A multi-day run carries it across midnight.
    initial_hours: Annotated[int, Field(ge=1)] | None = None
    provenance: dict[str, str] = {}

    @model_validator(mode="after")
    def _limits(self):
        if self.p_min > self.p_max:
            raise ValueError(f"p_min ({self.p_min}) > p_max ({self.p_max})")
        if self.p_initial is not None and self.initial_on and not self.p_min <= self.p_initial <= self.p_max:
            raise ValueError(f"p_initial ({self.p_initial}) outside [p_min, p_max] = [{self.p_min}, {self.p_max}]")
        if self.p_initial and not self.initial_on:
            raise ValueError(f"p_initial ({self.p_initial}) of a unit that is initially off must be 0")
        return self

    @property
    def keep_initial_hours(self) -> int:
        """Hours at the start of the day the unit must stay in its initial state: what its minimum up time (on) or
        down time (off) still asks after ``initial_hours`` in that state, 0 if nothing (6)-(7)."""
        if self.initial_hours is None:
            return 0
        return max(0, (self.min_up if self.initial_on else self.min_down) - self.initial_hours)

    @property
    def initial_output(self) -> float:
        """Output before the day starts, from which the first ramp (4)-(5) counts: p_initial, else P_min if on."""
        if not self.initial_on:
            return 0.0
        return self.p_min if self.p_initial is None else self.p_initial


class Renewable(_CaseModel):
    """A nondispatchable unit: its hourly availability forecast, which scenarios perturb."""

    name: str
    capacity: NonNeg
    forecast: Profile
    provenance: dict[str, str] = {}

    @model_validator(mode="after")
    def _within_capacity(self):
        worst = max(self.forecast)
        if worst > self.capacity:
            raise ValueError(f"forecast ({worst}) exceeds capacity ({self.capacity})")
        return self


class Storage(_CaseModel):
    """The energy storage i in S: power limits (8)-(9), energy (11)-(12), minimum charge/discharge times (13)-(14)."""

    name: str
    c_max: Pos
    p_dch_min: NonNeg
    p_dch_max: Pos
    p_ch_min: NonNeg
    p_ch_max: Pos
    min_charge: Duration
    min_discharge: Duration
    c_initial: NonNeg
    provenance: dict[str, str] = {}

    @model_validator(mode="after")
    def _limits(self):
        if self.p_dch_min > self.p_dch_max:
            raise ValueError(f"p_dch_min ({self.p_dch_min}) > p_dch_max ({self.p_dch_max})")
        if self.p_ch_min > self.p_ch_max:
            raise ValueError(f"p_ch_min ({self.p_ch_min}) > p_ch_max ({self.p_ch_max})")
        if self.c_initial > self.c_max:
            raise ValueError(f"c_initial ({self.c_initial}) > c_max ({self.c_max})")
        return self


class AdjustableLoad(_CaseModel):
    """An adjustable load d in D: power limits (15), energy E_d within [alpha, beta] (16), minimum operating time (17)."""

    name: str
    d_min: NonNeg
    d_max: Pos
    energy: Pos
    alpha: Hour
    beta: Hour
    min_up: Duration
    provenance: dict[str, str] = {}

    @model_validator(mode="after")
    def _deliverable(self):
        if self.d_min > self.d_max:
            raise ValueError(f"d_min ({self.d_min}) > d_max ({self.d_max})")
        if self.alpha > self.beta:
            raise ValueError(f"window alpha ({self.alpha}) > beta ({self.beta})")
        hours = self.beta - self.alpha + 1
        if self.energy > self.d_max * hours + 1e-9:
            raise ValueError(
                f"energy {self.energy} MWh cannot be delivered in hours {self.alpha}-{self.beta} "
                f"at d_max {self.d_max} MW (at most {self.d_max * hours:g} MWh)"
            )
        if self.min_up > hours:
            raise ValueError(f"min_up ({self.min_up} h) is longer than the window {self.alpha}-{self.beta}")
        return self


class Grid(_CaseModel):
    """The point of common coupling: P_M^max of (18), the DMO's award P^sch of (19), penalty c and value of lost load."""

    p_m_max: Pos
    p_sch: SignedProfile
    penalty: NonNeg
    voll: Pos
    iso_price: SignedProfile
    provenance: dict[str, str] = {}


class FixedLoad(_CaseModel):
    forecast: Profile
    provenance: dict[str, str] = {}


class Uncertainty(_CaseModel):
    """Half-widths of the uniform forecast errors, as fractions of the forecast."""

    load: Annotated[float, Field(ge=0, lt=1)]
    wind: Annotated[float, Field(ge=0, le=1)] = 0.0
    solar: Annotated[float, Field(ge=0, le=1)] = 0.0
    provenance: dict[str, str] = {}

    def for_renewable(self, name: str) -> float:
        """The error bound of a renewable: its own if named, else the wind bound."""
        return getattr(self, name, self.wind)


class CaseInfo(_CaseModel):
    name: str
    description: str = ""
    provenance: dict[str, str] = {}


class Case(_CaseModel):
    """A whole microgrid case. Array views (``unit_array`` and friends) feed the vectorised model."""

    case: CaseInfo
    grid: Grid
    fixed_load: FixedLoad
    uncertainty: Uncertainty
    units: Annotated[list[Unit], Field(min_length=1)]
    renewables: list[Renewable] = []
    storage: Storage | None = None
    loads: list[AdjustableLoad] = []

    @model_validator(mode="after")
    def _unique_names(self):
        names = [x.name for x in (*self.units, *self.renewables, *self.loads)]
        if self.storage is not None:
            names.append(self.storage.name)
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"names must be unique, repeated: {', '.join(dup)}")
        return self

    @property
    def name(self) -> str:
        return self.case.name

    def unit_array(self, field: str) -> np.ndarray:
        """One field of every unit, as an array over G."""
        return np.array([getattr(u, field) for u in self.units], dtype=float)

    def load_array(self, field: str) -> np.ndarray:
        """One field of every adjustable load, as an array over D."""
        return np.array([getattr(d, field) for d in self.loads], dtype=float)

    @property  # not cached: an array kept in the model's __dict__ would make two cases uncomparable (==)
    def load_windows(self) -> np.ndarray:
        """(D, 24) 0/1: hour t lies in [alpha_d, beta_d] of (16)."""
        hours = np.arange(1, HOURS + 1)
        return np.array([(d.alpha <= hours) & (hours <= d.beta) for d in self.loads], dtype=float).reshape(
            len(self.loads), HOURS
        )

    def with_grid(self, **changes) -> "Case":
        """A copy with grid fields replaced (award, penalty...), validated again."""
        return self.model_validate({**self.model_dump(), "grid": {**self.grid.model_dump(), **changes}})


def _field_path(loc: tuple, data: dict) -> str:
    """Render a pydantic error location as ``units[G3].p_min``, using names where the list items have them."""
    out, node = "", data
    for part in loc:
        if isinstance(part, int):
            item = node[part] if isinstance(node, list) and part < len(node) else None
            label = item.get("name") if isinstance(item, dict) else None
            out += f"[{label or part}]"
            node = item
        else:
            out += f".{part}" if out else str(part)
            node = node.get(part) if isinstance(node, dict) else None
    return out


def parse_case(data: dict, source: str = "<case>") -> Case:
    """Validate a case given as a dict; any problem raises CaseError naming the source and the field."""
    try:
        return Case.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = _field_path(tuple(err["loc"]), data)
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "missing":
            msg = "missing field"
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        raise CaseError(f"{source}: {where or 'case'}: {msg}{more}") from None


def case_toml(case: Case, comment: str = "") -> str:
    """The case as a case file that ``load_case`` reads back to the same case (what is None left out: its default)."""
    return toml_text(case.model_dump(exclude_none=True), comment)


def case_path(name_or_path: str | Path) -> Path:
    """A built-in case name (``paper``) or a path to a TOML file."""
    builtin = DATA_DIR / f"{name_or_path}.toml"
    if builtin.is_file():
        return builtin
    return Path(name_or_path)


def load_case(name_or_path: str | Path) -> Case:
    """Read and validate a case file; raises CaseError with one line naming the file and the field."""
    path = case_path(name_or_path)
    data = read_toml(path, "case", CaseError, f" (built-in cases: {', '.join(builtin_cases())})")
    return parse_case(data, str(path))


def read_toml(path: Path, what: str, error: type[Exception], missing_hint: str = "") -> dict:
    """A TOML file (case, fleet, experiment...) as a dict; a file that is missing, unreadable, not a regular file,
    larger than ``MAX_TOML_BYTES`` or not TOML raises ``error`` with one line naming it."""
    return parse_toml(read_text(path, what, error, MAX_TOML_BYTES, missing_hint), str(path), error)


def read_text(path: Path, what: str, error: type[Exception], limit: int, missing_hint: str = "") -> str:
    """A file's text, before anything parses it: a file that is missing, unreadable, not a regular file, larger than
    ``limit`` bytes (its size is checked before it is read, and again as it is read: it may grow) or not UTF-8
    raises ``error`` with one line naming it."""
    path = Path(path)
    try:
        raw = None
        info = path.stat()
        # a FIFO or /dev/zero would block or never end, and a file too large is not read at all
        if stat.S_ISREG(info.st_mode) and info.st_size <= limit:
            with path.open("rb") as f:
                raw = f.read(limit + 1)
    except FileNotFoundError:
        raise error(f"{what} file not found: {path}{missing_hint}") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise error(f"cannot read {what} file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISREG(info.st_mode):
        raise error(f"cannot read {what} file {path}: not a regular file")
    if raw is None or len(raw) > limit:
        raise error(f"{path}: larger than {limit:,} bytes, the most a {what} file may hold")
    try:
        return raw.decode()
    except UnicodeDecodeError as exc:
        raise error(f"cannot read {what} file {path}: {exc}") from None


def parse_toml(text: str, source: str, error: type[Exception]) -> dict:
    """TOML text as a dict, within ``MAX_TOML_BYTES`` and ``MAX_TOML_DEPTH``; else ``error``, one line naming
    ``source``."""
    if len(text) > MAX_TOML_BYTES:
        raise error(f"{source}: larger than {MAX_TOML_BYTES:,} bytes, the most a TOML document may hold")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{source}: nested deeper than {MAX_TOML_DEPTH} levels") from None
    except ValueError:  # an integer of more digits than Python converts (sys.get_int_max_str_digits)
        digits = sys.get_int_max_str_digits()
        raise error(f"{source}: not valid TOML: an integer of more than {digits} digits") from None
    if toml_depth(data) > MAX_TOML_DEPTH:
        raise error(f"{source}: nested deeper than {MAX_TOML_DEPTH} levels")
    return data


def toml_depth(data: object) -> int:
    """How deeply tables and arrays nest in ``data`` (a document of scalars only is 1), counted without recursion
    and no further than one level past ``MAX_TOML_DEPTH``."""
    deepest, stack = 0, [(data, 1)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if depth > MAX_TOML_DEPTH:
            break
        children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else ()
        stack.extend((child, depth + 1) for child in children if isinstance(child, (dict, list)))
    return deepest


def builtin_cases() -> list[str]:
    return sorted(p.stem for p in DATA_DIR.glob("*.toml"))
