"""Study specs (rigctl.apps.study.spec), the results table (table) and the report's statistics (report):
what a spec expands to, the ids that make resuming possible, one clear line for a bad spec."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from rigctl.apps.study.report import summarise, t_interval, wilson
from rigctl.apps.study.spec import load_spec, spec_from_dict
from rigctl.apps.study.table import ResultsTable
from rigctl.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def _spec(**data):
    return spec_from_dict({"run": {"command": "plan reachable", "args": {"disk": True}}, **data},
                          Path("/tmp"))


def test_a_product_of_parameters_times_seeds_gives_every_combination_once() -> None:
    spec = _spec(parameters={"d12": [0.1, 0.3], "moves": [2, 4, 6]}, seeds={"count": 4})
    combos = {(c.parameters["d12"], c.parameters["moves"], c.seed) for c in spec.cases}
    assert len(spec.cases) == 2 * 3 * 4 == len(combos)
    assert {c.seed for c in spec.cases} == {0, 1, 2, 3}
    assert all(c.options["disk"] is True and c.options["seed"] == c.seed for c in spec.cases)


def test_listed_cases_are_crossed_with_the_product_and_override_args() -> None:
    spec = _spec(cases=[{"cells": 31}, {"cells": 41}], parameters={"moves": [2, 4]})
    assert sorted((c.options["cells"], c.options["moves"]) for c in spec.cases) == [
        (31, 2), (31, 4), (41, 2), (41, 4)]


def test_a_range_parameter_gives_its_values_without_float_creep() -> None:
    spec = _spec(parameters={"d12": {"start": 0.05, "stop": 0.3001, "step": 0.05}})
    assert [c.parameters["d12"] for c in spec.cases] == [0.05, 0.1, 0.15, 0.2, 0.25, 0.3]


def test_case_ids_depend_on_what_runs_not_on_the_order_of_the_spec() -> None:
    a = _spec(parameters={"d12": [0.1, 0.3], "moves": [2, 4]})
    b = _spec(parameters={"moves": [4, 2], "d12": [0.3, 0.1]})
    assert {c.id for c in a.cases} == {c.id for c in b.cases}
    c = _spec(parameters={"d12": [0.1, 0.3], "moves": [2, 6]})
    assert len({x.id for x in a.cases} & {x.id for x in c.cases}) == 2  # only moves 2 shared


@pytest.mark.parametrize("data, named", [
    ({"run": {"command": "plan nothing"}}, "run.command"),
    ({"run": {"args": {}}}, "run.command"),
    ({"run": {"command": "plan rrt"}, "parameters": {"k": 4}}, "parameters.k"),
    ({"run": {"command": "plan rrt"}, "seeds": {"count": 0}}, "seeds.count"),
    ({"run": {"command": "plan rrt"}, "sedes": 3}, "sedes"),
    ({"run": {"command": "execute", "args": {}}}, "run.args.plan"),
    ({"run": {"command": "execute", "args": {"plan": "p.json", "slipp": 0.8}}}, "slipp"),
    ({"run": {"command": "execute", "args": {"plan": "p.json", "fault": {"kind": "stall"}}}}, "fault"),
])
def test_a_bad_spec_is_refused_naming_the_key(data, named) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        spec_from_dict(data, Path("/tmp"))


def test_the_cli_refuses_a_bad_spec_with_one_line_and_exit_2(tmp_path) -> None:
    spec = tmp_path / "bad.toml"
    spec.write_text('[run]\ncommand = "plan reachable"\nargs = { disk = true, d12 = 0.3, '
                    'moves = 2, cells = 3 }\n')  # refused by the planner's own check, per case
    done = subprocess.run([sys.executable, "-m", "rigctl", "study", str(spec), "--serial",
                           "-o", str(tmp_path / "out")], capture_output=True, text=True, check=False)
    assert done.returncode == 1, done.stderr  # the case ran and was refused: its row says why
    table = pq.read_table(tmp_path / "out" / "results.parquet").to_pylist()
    assert table[0]["status"] == "bad_input" and "--cells" in table[0]["message"]
    spec.write_text('[run]\ncommand = "plan reachable"\nargs = { disk = true, d12 = 0.3, '
                    'moves = 2, cellz = 3 }\n')  # an option the planner does not have
    done = subprocess.run([sys.executable, "-m", "rigctl", "study", str(spec), "--serial",
                           "-o", str(tmp_path / "out2")], capture_output=True, text=True, check=False)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "cellz" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "out2").exists()


def test_every_shipped_study_loads() -> None:
    names = {p.stem: load_spec(p) for p in (ROOT / "studies").glob("*.toml")
             if p.name != "five-mm-turns.toml"}
    assert {"rrt-solve", "reachable", "reachable-quick", "closed-loop", "coilboard-delivery"} <= set(names)
    assert len(names["reachable"].cases) == 16 * 7
    assert len(names["closed-loop"].cases) == 20


def test_the_table_keeps_rows_through_a_reopen_and_replaces_a_case_by_id(tmp_path) -> None:
    table = ResultsTable(tmp_path)
    row = {"case_id": "a", "seed": 1, "status": "failed", "message": "x", "success": None,
           "error": None, "wall_s": 0.5, "record": "r", "worker": "w",
           "parameters": {"start": [[1.0, 2.0]], "k": 4}, "figures": {"solved": False}}
    table.add(row)
    table.add({**row, "case_id": "b", "status": "ok"})
    again = ResultsTable(tmp_path)
    assert again.done_ids() == {"a", "b"} and again.done_ids(retry_failed=True) == {"b"}
    again.add({**row, "status": "ok", "figures": {"solved": True, "distance": 0.5}})
    rows = {r["case_id"]: r for r in pq.read_table(tmp_path / "results.parquet").to_pylist()}
    assert len(rows) == 2 and rows["a"]["status"] == "ok" and rows["a"]["fig_solved"] is True
    assert rows["a"]["start"] == "[[1.0, 2.0]]" and rows["b"]["fig_distance"] is None


def test_a_study_killed_between_two_writes_of_the_table_keeps_every_finished_case(tmp_path,
                                                                                 monkeypatch) -> None:
    from rigctl.apps.study import table as results

    monkeypatch.setattr(results, "WRITE_EVERY_S", 1e9)  # after the first, no write until asked
    row = {"case_id": "a", "seed": 1, "status": "ok", "message": "", "success": True,
           "error": 0.5, "wall_s": 0.5, "record": "r", "worker": "w",
           "parameters": {"k": 4}, "figures": {"solved": True}}
    table = ResultsTable(tmp_path)
    table.add(row)  # the first add writes the table
    table.add({**row, "case_id": "b", "parameters": {"k": 5}})
    on_disk = pq.read_table(tmp_path / "results.parquet").to_pylist()
    assert [r["case_id"] for r in on_disk] == ["a"]  # b is in the journal only
    with open(tmp_path / "results.journal.jsonl", "a") as journal:
        journal.write('{"case_id": "c", "sta')  # killed in the middle of a line
    resumed = ResultsTable(tmp_path)  # as `rigctl study` does when run again
    assert resumed.done_ids() == {"a", "b"}
    assert {r["case_id"]: r["k"] for r in results.read_results(tmp_path).to_pylist()} == {"a": 4, "b": 5}
    resumed.write()
    assert {r["case_id"] for r in pq.read_table(tmp_path / "results.parquet").to_pylist()} == {"a", "b"}
    assert not (tmp_path / "results.journal.jsonl").exists()


def test_the_wilson_interval_matches_its_closed_form() -> None:
    # 0 of 10: [0, z^2 / (n + z^2)]; 5 of 10 symmetric about 0.5
    low, high = wilson(0, 10)
    z2 = 1.959963984540054 ** 2
    assert low == pytest.approx(0.0, abs=1e-12) and high == pytest.approx(z2 / (10 + z2))
    low, high = wilson(5, 10)
    assert low + high == pytest.approx(1.0) and high == pytest.approx(0.7634, abs=1e-4)


def test_the_t_interval_of_1_2_3_is_2_plus_minus_2_484() -> None:
    mean, low, high = t_interval([1.0, 2.0, 3.0])  # s = 1, t(0.975, 2) = 4.302653
    half = 4.302653 / math.sqrt(3)
    assert mean == 2.0 and (low, high) == (pytest.approx(2.0 - half, rel=1e-6),
                                            pytest.approx(2.0 + half, rel=1e-6))


def test_the_error_interval_is_over_seeds_one_sample_per_seed() -> None:
    # two cases per seed at x = 1: the seed means are 1, 2, 3 -> the interval of [1, 2, 3]
    rows = [{"x": 1, "seed": s, "error": s + 1 + d} for s in range(3) for d in (-0.5, 0.5)]
    (point,) = summarise(rows, "x", "error", share=False)
    assert point["n"] == 6 and point["mean"] == pytest.approx(2.0)
    assert point["high"] - 2.0 == pytest.approx(4.302653 / math.sqrt(3), rel=1e-6)


def test_a_cases_rig_overrides_are_checked_by_its_own_rig_kinds_model() -> None:
    """`rig.SECTION.KEY` of an execute case: the rig file is validated again by its rig kind's
    model (the kind's own tables are not the common model's): a key of the kind's own table is
    overridden, a key that table lacks and a value out of its range are refused in one line."""
    from rigctl.apps.study.cases import _override
    from rigctl.core.registry import rig_kind

    board = rig_kind("coil-board")
    rig = board.bench_rig()
    changed = _override(rig, {"board.max_command": 100, "stream.reply_timeout_s": 2.0})
    assert isinstance(changed, board.settings())
    assert changed.board.max_command == 100 and changed.stream.reply_timeout_s == 2.0
    with pytest.raises(ConfigError, match="no key 'microsteps'"):
        _override(rig, {"board.microsteps": 16})
    with pytest.raises(ConfigError, match="max_command") as refused:
        _override(rig, {"board.max_command": 0})
    assert "\n" not in str(refused.value)
