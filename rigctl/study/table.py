"""A study's results: one Parquet table, a row per finished case, rewritten whole (a temporary file
renamed over the old one) each time a case finishes, so the table on disk is always complete and
readable, and a study stopped at any instant resumes from it.

Columns: `case_id`, `seed`, `status` (ok, bad_input, failed, error), `message`, `success`,
`error`, `wall_s`, `cpu_s` (the worker process's CPU time: a planner's own; an emulated run's
children not counted), `started_s` (when it started, s since the epoch), `record` (the plan written or the run record's folder), `worker`,
`finished_at` (UTC, ISO 8601); then one column per parameter (its own name) and one per figure the
command reported (`fig_<name>`). A value that is not a number, a flag or a text (a list of
points) is kept as its JSON text.
"""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

TABLE_NAME = "results.parquet"
FIXED = ["case_id", "seed", "status", "message", "success", "error", "wall_s", "cpu_s", "started_s",
         "record", "worker", "finished_at"]
TYPES = {"seed": pa.int64(), "success": pa.bool_(), "error": pa.float64(), "wall_s": pa.float64(), "cpu_s": pa.float64(),
         "started_s": pa.float64()}


def flat_row(result: dict[str, Any]) -> dict[str, Any]:
    """A case's result (cases.run_case) as one flat row of the table."""
    row = {key: result.get(key) for key in FIXED}
    row["finished_at"] = row["finished_at"] or datetime.datetime.now(datetime.UTC).isoformat(
        timespec="seconds")
    for name, value in result.get("parameters", {}).items():
        row[name] = value
    for name, value in result.get("figures", {}).items():
        row[f"fig_{name}"] = value
    return row


def _column(values: list[Any], kind: pa.DataType | None = None) -> pa.Array:
    present = [v for v in values if v is not None]
    if kind is not None:
        return pa.array(values, type=kind)
    if not present:
        return pa.array(values, type=pa.string())
    if all(isinstance(v, bool) for v in present):
        return pa.array(values, type=pa.bool_())
    if all(isinstance(v, int) and not isinstance(v, bool) for v in present) and present:
        return pa.array(values, type=pa.int64())
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present) and present:
        return pa.array([None if v is None else float(v) for v in values], type=pa.float64())
    return pa.array([None if v is None else v if isinstance(v, str) else json.dumps(v)
                     for v in values], type=pa.string())


class ResultsTable:
    """The rows of `folder/results.parquet`: read at start, one row added per finished case."""

    def __init__(self, folder: str | Path) -> None:
        self.path = Path(folder) / TABLE_NAME
        self.rows: list[dict[str, Any]] = []
        if self.path.exists():
            self.rows = pq.read_table(self.path).to_pylist()

    def done_ids(self, *, retry_failed: bool = False) -> set[str]:
        """Ids of the cases already in the table (with `retry_failed`: only those that ran ok)."""
        return {r["case_id"] for r in self.rows if not retry_failed or r["status"] == "ok"}

    def add(self, result: dict[str, Any]) -> None:
        """Add (or replace, by case id) one case's row and write the table."""
        row = flat_row(result)
        self.rows = [r for r in self.rows if r["case_id"] != row["case_id"]] + [row]
        self.write()

    def write(self) -> None:
        names = list(dict.fromkeys(FIXED + [k for r in self.rows for k in r]))
        table = pa.table({n: _column([r.get(n) for r in self.rows], TYPES.get(n)) for n in names})
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, self.path)  # whole or not at all


def read_results(folder_or_file: str | Path) -> pa.Table:
    """A study's table, from its folder or the Parquet file itself."""
    path = Path(folder_or_file)
    return pq.read_table(path / TABLE_NAME if path.is_dir() else path)
