"""Bounds of what the scenarios package reads and draws (docs/experiments.md, "Bounds"): TOML files in size and
depth, fleets in members, scales and seeds, seeds and every seed derived from one, samples and scenario sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from messages.schemas import MAX_AGENTS, MAX_DAYS
from microgrid_agent.solvers.evaluation import fresh_seed, replication_seed
from scenarios.case import MAX_TOML_BYTES, MAX_TOML_DEPTH, CaseError, load_case, parse_toml, read_toml
from scenarios.days import MAX_SEED, day_seed, market_days
from scenarios.fleet import MAX_MEMBERS, MAX_SCALE, FleetError, load_fleet, make_fleet
from scenarios.generation import MAX_SAMPLE, MAX_SCENARIOS, make_scenarios, sample



def test_a_fleet_file_holds_at_most_the_day_summarys_agents(tmp_path):
    def fleet(n: int) -> Path:
        path = tmp_path / f"fleet{n}.toml"
        path.write_text("".join(f'[[agents]]\nid = "mg{i}"\nscale = 1.5\n' for i in range(1, n + 1)))
        return path

    assert len(load_fleet(fleet(MAX_MEMBERS))) == MAX_MEMBERS
    with pytest.raises(FleetError, match=f"{MAX_MEMBERS + 1} agents; a fleet has at most {MAX_MEMBERS}"):
        load_fleet(fleet(MAX_MEMBERS + 1))
    assert len(make_fleet(MAX_MEMBERS)) == MAX_MEMBERS
    assert MAX_MEMBERS == MAX_AGENTS  # a fleet holds as many agents as the day summary lists
    with pytest.raises(ValueError, match="1..1024 members"):
        make_fleet(MAX_MEMBERS + 1)
    (tmp_path / "scaled.toml").write_text(f'[[agents]]\nid = "mg1"\nscale = {MAX_SCALE + 0.5}\n')
    with pytest.raises(FleetError, match=r"scale: must be a number in \(0, 10\]"):
        load_fleet(tmp_path / "scaled.toml")
    (tmp_path / "seeded.toml").write_text(f'[[agents]]\nid = "mg1"\nseed = {MAX_SEED + 1}\n')
    with pytest.raises(FleetError, match="seed must be an integer in 0..4294967295"):
        load_fleet(tmp_path / "seeded.toml")


def test_a_toml_file_is_bounded_in_size_and_depth(tmp_path):
    def nested(depth: int) -> str:  # the document is level 1, each array one more
        return "a = " + "[" * (depth - 1) + "]" * (depth - 1) + "\n"

    parse_toml(nested(MAX_TOML_DEPTH), "x", CaseError)
    for text in (nested(MAX_TOML_DEPTH + 1), nested(100_000)):
        with pytest.raises(CaseError, match=f"x: nested deeper than {MAX_TOML_DEPTH} levels"):
            parse_toml(text, "x", CaseError)
    with pytest.raises(CaseError, match="an integer of more than"):
        parse_toml("a = " + "9" * 10_000, "x", CaseError)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (MAX_TOML_BYTES - 3) + "\n")
    assert read_toml(big, "case", CaseError) == {}
    big.write_text("# " + "x" * (MAX_TOML_BYTES - 2) + "\n")
    with pytest.raises(CaseError, match=f"larger than {MAX_TOML_BYTES:,} bytes, the most a case file may hold"):
        read_toml(big, "case", CaseError)
    for special in ("/dev/zero", str(tmp_path)):  # one would never end, the other is no file
        with pytest.raises(CaseError, match="not a regular file"):
            load_case(special)
    with pytest.raises(CaseError, match="embedded null byte"):
        load_case("a\x00b")


def test_every_seed_derived_from_one_in_range_is_valid():
    """The largest seed's derived seeds (last day's, its realised day's, a fleet's, an evaluation's, a replication's)
    are non-negative and below 2**33, and numpy takes them."""
    derived = [day_seed(MAX_SEED, MAX_DAYS) + 1000, fresh_seed(MAX_SEED), replication_seed(MAX_SEED, 99),
               *(m.seed for m in make_fleet(5, seed=MAX_SEED))]
    assert all(0 <= s < 2**33 for s in derived), derived
    for s in derived:
        np.random.default_rng([s, 7]).integers(0, 24)
    case = load_case("paper")
    assert sample(case, 1, 1, seed=derived[0]).S == 1
    with pytest.raises(ValueError, match="seed must be an integer in 0..4294967295"):
        make_fleet(2, seed=-1)


def test_samples_and_scenarios_are_bounded_where_they_are_drawn():
    case = load_case("paper")
    with pytest.raises(ValueError, match=f"1..{MAX_SAMPLE} scenarios"):
        sample(case, MAX_SAMPLE + 1, 1)
    with pytest.raises(ValueError, match=f"1..{MAX_SCENARIOS} scenarios"):
        make_scenarios(case, MAX_SCENARIOS + 1, 1)
    with pytest.raises(ValueError, match=f"at most {MAX_SAMPLE}"):
        make_scenarios(case, 2, 1, sample_size=MAX_SAMPLE + 1)
    assert market_days("9999-12-30", 2)[-1] == "9999-12-31"
    with pytest.raises(ValueError, match="end after 9999-12-31"):
        market_days("9999-12-31", 2)
