"""A pandapower JSON is read as data (scenarios/pandapower_json.py; docs/network.md, "A pandapower net as a feeder"):
pandapower's own feeder written by ``pandapower.to_json`` reads back as the built-in exactly, nothing a file names is
imported, a file too large is refused from its size, and whatever JSON a file holds gives a feeder or one line."""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenarios.network import Network, NetworkError, ieee33, load_network
from scenarios.pandapower_json import MAX_NETWORK_BYTES, NET, TABLE


def frame(columns: list[str], rows: list[list], **extra) -> dict:
    split = {"columns": columns, "index": list(range(len(rows))), "data": rows}
    return {"_module": TABLE[0], "_class": TABLE[1], "_object": json.dumps(split), "orient": "split", **extra}


def two_buses(**tables) -> dict:
    """A net of two buses and a line, as pandapower writes one, with ``tables`` replacing or adding its tables."""
    net = {"bus": frame(["vn_kv", "in_service"], [[12.47, True], [12.47, True]]),
           "ext_grid": frame(["bus", "in_service"], [[0, True]]),
           "line": frame(["from_bus", "to_bus", "length_km", "r_ohm_per_km", "x_ohm_per_km", "max_i_ka", "parallel",
                          "in_service"], [[0, 1, 2.0, 0.25, 0.5, 0.2, 1, True]]),
           "load": frame(["bus", "p_mw", "q_mvar", "scaling", "in_service"], [[1, 0.5, 0.2, 1.0, True]]),
           "std_types": {"line": {"a cable": {"r_ohm_per_km": 0.1}}}, **tables}
    return {"_module": NET[0], "_class": NET[1], "_object": net}


def write(tmp_path, doc, name="net.json"):
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def test_pandapowers_case33bw_written_and_read_back_is_ieee33_exactly(tmp_path):
    import pandapower as pp
    import pandapower.networks as pn

    path = tmp_path / "ieee33.json"
    pp.to_json(pn.case33bw(), str(path))
    read, built = load_network(path), ieee33()
    for field in dataclasses.fields(Network):
        a, b = getattr(read, field.name), getattr(built, field.name)
        assert (np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b), field.name


def test_a_small_net_reads_as_its_tables_say(tmp_path):
    net = load_network(write(tmp_path, two_buses()))
    assert (net.name, net.buses, net.substation, net.base_kv) == ("net", ("0", "1"), "0", 12.47)
    assert net.r_ohm.tolist() == [0.5] and net.x_ohm.tolist() == [1.0]
    assert net.s_max_mva.tolist() == pytest.approx([np.sqrt(3) * 12.47 * 0.2])
    assert (net.load_p_mw.tolist(), net.load_q_mvar.tolist()) == ([0.0, 0.5], [0.0, 0.2])


@pytest.mark.parametrize("module", ["this", "dmosim_evil_feeder"])
def test_a_module_a_file_names_is_never_imported(tmp_path, monkeypatch, capfd, module):
    (tmp_path / "dmosim_evil_feeder.py").write_text(f"open({str(tmp_path / 'imported')!r}, 'w').close()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    already = module in sys.modules
    for doc in ({"_module": module, "_class": "pandapowerNet", "_object": {}},  # as the top level
                two_buses(bus={"_module": module, "_class": "DataFrame", "_object": "{}"}),  # as a table
                two_buses(std_types={"x": [{"_module": module, "_class": "f"}]})):  # anywhere
        with pytest.raises(NetworkError, match=f"names _module '{module}'") as err:
            load_network(write(tmp_path, doc))
        assert "\n" not in str(err.value)
    assert not (tmp_path / "imported").exists() and (module in sys.modules) == already
    assert capfd.readouterr() == ("", "")  # import this prints the Zen of Python


@pytest.mark.parametrize("doc, message", [
    ("{", "not a pandapower JSON: Expecting property name"),
    ("[" * 100_000, "not a pandapower JSON: nested too deep"),
    ("1" * 5000, "not a pandapower JSON: Exceeds the limit"),
    ({"bus": {}}, "its top level must be"),
    (two_buses(line=two_buses()), "a pandapower net or table inside something else"),
    (two_buses(std_types={"line": frame(["a"], [])}), "a pandapower net or table inside something else"),
    (two_buses(load={**frame(["bus"], []), "_object": json.dumps({"columns": ["bus"], "index": [], "data": [],
                                                                  "x": {"_module": "os", "_class": "system"}})}),
     "names _module 'os'"),
    (two_buses(line={"_module": TABLE[0], "_class": TABLE[1], "_object": "{}", "orient": "records"}),
     "table line: written in orient 'records'"),
    (two_buses(line=frame(["from_bus"], [[0]])), "table line: no column 'to_bus'"),
    (two_buses(bus=frame(["vn_kv", "vn_kv"], [[1, 1]])), "table bus: its columns must be distinct strings"),
    (two_buses(bus=frame(["vn_kv", "in_service"], [[12.47]])), "table bus: 1 row labels and 1 rows"),
    ({"_module": NET[0], "_class": NET[1], "_object": {"ext_grid": frame(["bus", "in_service"], [])}},
     "no table 'bus'"),
    (two_buses(trafo=frame(["hv_bus"], [[0]])), "has transformers"),
    (two_buses(ext_grid=frame(["bus", "in_service"], [[0, False]])), "needs exactly one external grid"),
    (two_buses(load=frame(["bus", "p_mw", "q_mvar", "scaling", "in_service"], [[7, 1.0, 0.0, 1.0, True]])),
     "load 0 is in service at bus 7, which is not a bus in service"),
    (two_buses(load=frame(["bus", "p_mw", "q_mvar", "scaling", "in_service"], [[1, 1e308, 0.0, 1.0, True]])),
     r"bus 1 p_mw must be >= -10,000 and <= 10,000, got 1e\+308"),
    (two_buses(load=frame(["bus", "p_mw", "q_mvar", "scaling", "in_service"], [[1, 1.0, 0.0, 1.0, 1]])),
     "load 0 in_service must be true or false, got 1"),
    (two_buses(line=frame(["from_bus", "to_bus", "length_km", "r_ohm_per_km", "x_ohm_per_km", "max_i_ka", "parallel",
                           "in_service"], [[0, 1, 2.0, 0.25, 0.5, 0.2, 0, True]])),
     "line 0 parallel must be a whole number of circuits >= 1, got 0"),
    (two_buses(bus=frame(["vn_kv", "in_service"], [[12.47, True], [11.0, True]])), "buses at several voltages"),
])
def test_what_cannot_be_read_is_one_line_naming_the_file(tmp_path, doc, message):
    path = write(tmp_path, doc)
    with pytest.raises(NetworkError, match=message) as err:
        load_network(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_file_too_large_is_refused_from_its_size_without_reading_it(tmp_path):
    path = tmp_path / "huge.json"
    with path.open("wb") as f:
        f.truncate(200_000_000)  # sparse: no disk, and not JSON either; its size alone refuses it
    with pytest.raises(NetworkError, match=f"huge.json: larger than {MAX_NETWORK_BYTES:,} bytes"):
        load_network(path)
    write(tmp_path, " " * (MAX_NETWORK_BYTES - 1) + json.dumps(two_buses()), "big.json")
    with pytest.raises(NetworkError, match="larger than"):
        load_network(tmp_path / "big.json")


JSON = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=5),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(
                        ["_module", "_class", "_object", "orient", "columns", "index", "data", "bus", "x"]), inner,
                        max_size=3), max_leaves=8)
CELLS = st.one_of(st.none(), st.booleans(), st.floats(), st.integers(-3, 3), st.text(max_size=2), st.just([]))


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["top", "object", "table", "split", "cell"]), JSON, CELLS, st.integers(0, 7))
def test_whatever_json_a_file_holds_gives_a_feeder_or_one_line(tmp_path_factory, where, value, cell, column):
    doc = two_buses()
    if where == "top":
        doc = value
    elif where == "object":
        doc["_object"]["bus"] = value
    elif where == "table":
        doc["_object"]["line"]["orient"] = value
    elif where == "split":
        doc["_object"]["line"]["_object"] = json.dumps(value)
    else:
        split = json.loads(doc["_object"]["line"]["_object"])
        split["data"][0][column] = cell
        doc["_object"]["line"]["_object"] = json.dumps(split)
    path = write(tmp_path_factory.mktemp("net"), doc)
    try:
        assert load_network(path).n_buses == 2
    except NetworkError as err:
        assert "\n" not in str(err)
