"""The run record: a directory written as the run goes, so a crash loses nothing before the crash.

Layout of `runs/<UTC time>-<plan name>/`:
- `plan.json`: the plan as executed (with `expected` filled);
- `rig.toml`: the rig configuration snapshot;
- `events.jsonl`: append-only event log, one JSON object per line, `{"t": s since start, "event": ...}`;
- `channels.json`: what the stream commands and measures (`rigctl.core.channels.Channel`: name, unit,
  limits, group), written when the stream opens;
- `stream.csv`: the per-cycle journal: t, sample index, move index, each channel commanded and
  measured (columns `cmd_<name>_<unit>`, `meas_<name>_<unit>`: amps, drive units, radians);
- `stream/part-NNNNN.parquet`: the same time series (plus the period error) in Parquet, in parts;
- `summary.json`: written last; its absence means the run did not finish.

Why Parquet: a lab opens it in one line from pandas, polars, MATLAB (`parquetread`) or R (arrow),
with typed columns, compression and the channels (names, units, limits) in the file's metadata; HDF5 would do
as well for reading, but a single HDF5 file being appended to is not readable after a crash
without SWMR and `h5clear`, whereas a Parquet file is immutable once written.

How a crash stays readable: the text files are flushed line by line (line-buffered; at 1 kHz a few
microseconds per cycle). The Parquet series is cut into parts of a few seconds; the stream thread
only fills an in-memory buffer, and a writer thread writes each full part to a temporary name and
renames it, so a part either exists whole or not at all. After a crash the parts hold everything
but the last few seconds, and `read_stream` takes those from the journal (`stream.csv`), skipping
a line cut in half.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import os
import queue
import re
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from rigctl.core.channels import Channel, channels_from_dicts

log = logging.getLogger(__name__)

PART_SECONDS = 5.0
MIN_PART_ROWS = 250


class StreamParquet:
    """The per-cycle series as Parquet parts in `folder`; `append` is for the stream thread and
    does no I/O (a full part goes to the writer thread). Each channel in its unit, times in s."""

    def __init__(self, folder: Path, channels: list[Channel], part_rows: int) -> None:
        # Import pyarrow now, before the stream starts: importing it on the writer thread at the
        # first part held the interpreter for ~180 ms and stalled the stream loop once per run.
        import pyarrow.parquet  # noqa: F401

        self.folder = folder
        self.folder.mkdir(exist_ok=True)
        self.channels = list(channels)
        self.part_rows = max(1, part_rows)
        self._parts = 0
        self._new_buffer()
        self._queue: queue.Queue = queue.Queue()
        self._writer = threading.Thread(target=self._write_parts, name="record-parquet",
                                        daemon=True)
        self._writer.start()

    def _new_buffer(self) -> None:
        n, c = self.part_rows, len(self.channels)
        self._t = np.empty(n)
        self._sample = np.empty(n, dtype=np.int64)
        self._move = np.empty(n, dtype=np.int32)
        self._cmd = np.empty((n, c))
        self._meas = np.empty((n, c))
        self._err = np.full(n, np.nan)
        self._rows = 0

    def append(self, t: float, sample: int, move: int, commanded, measured,
               period_error_s: float | None) -> None:
        k = self._rows
        self._t[k], self._sample[k], self._move[k] = t, sample, move
        self._cmd[k] = commanded
        self._meas[k] = measured
        if period_error_s is not None:
            self._err[k] = period_error_s
        self._rows = k + 1
        if self._rows == self.part_rows:
            self._hand_over()

    def _hand_over(self) -> None:
        if self._rows == 0:
            return
        r = self._rows
        self._queue.put((self._parts, self._t[:r], self._sample[:r], self._move[:r],
                         self._cmd[:r], self._meas[:r], self._err[:r]))
        self._parts += 1
        self._new_buffer()

    def _write_parts(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                write_stream_part(self.folder, self.channels, *item)
            except Exception:  # the journal still has these rows; never kill the run for it
                log.exception("writing a Parquet part failed; the rows stay in stream.csv")

    def close(self) -> None:
        self._hand_over()
        self._queue.put(None)
        self._writer.join(timeout=30)


def write_stream_part(folder: Path, channels: list[Channel], index: int, t, sample, move, cmd,
                      meas, period_error) -> Path:
    """Write one part atomically (temporary name, then rename); returns its path."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns = {"t_s": pa.array(t), "sample": pa.array(sample), "move": pa.array(move)}
    for j, channel in enumerate(channels):
        columns[channel.column("cmd")] = pa.array(np.ascontiguousarray(cmd[:, j]))
    for j, channel in enumerate(channels):
        columns[channel.column("meas")] = pa.array(np.ascontiguousarray(meas[:, j]))
    columns["period_error_s"] = pa.array(period_error)
    table = pa.table(columns).replace_schema_metadata({
        "rigctl.core.channels": json.dumps([c.as_dict() for c in channels]),
        "rigctl.units": json.dumps({"t_s": "s since the run started",
                                    "cmd_<name>_<unit>": "the channel's unit",
                                    "period_error_s": "s (start - due)"}),
    })
    final = folder / f"part-{index:05d}.parquet"
    tmp = folder / f".part-{index:05d}.parquet.tmp"
    pq.write_table(table, tmp)
    os.replace(tmp, final)
    return final


class RunRecord:
    def __init__(self, root: str | Path, plan_name: str) -> None:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        safe_name = re.sub(r"[^A-Za-z0-9_.-]+", "-", plan_name).strip("-") or "plan"
        self.path = Path(root) / f"{stamp}-{safe_name}"
        self.path.mkdir(parents=True, exist_ok=False)
        self.t0 = time.monotonic()  # event and stream times are seconds since this
        self._lock = threading.Lock()  # events come from the stream thread and the daemon's
        self._events: TextIO = open(self.path / "events.jsonl", "a", buffering=1)
        self._stream: TextIO | None = None
        self._parquet: StreamParquet | None = None
        self._series: list[Series] = []

    def write_file(self, name: str, text: str) -> None:
        (self.path / name).write_text(text)

    def event(self, event: str, **fields: Any) -> None:
        entry = {"t": round(time.monotonic() - self.t0, 6), "event": event, **fields}
        line = json.dumps(entry, default=_jsonable) + "\n"
        with self._lock:
            if not self._events.closed:
                self._events.write(line)

    def open_stream(self, channels: list[Channel] | list[str], rate_hz: float = 100.0) -> None:
        """Start the per-cycle series of `channels` (plain names: currents in A)."""
        channels = [c if isinstance(c, Channel) else Channel(c, "A") for c in channels]
        self.channels = channels
        self.write_file("channels.json", json.dumps([c.as_dict() for c in channels], indent=1))
        self._stream = open(self.path / "stream.csv", "a", buffering=1)
        header = ["t_s", "sample", "move"]
        header += [c.column("cmd") for c in channels] + [c.column("meas") for c in channels]
        self._stream.write(",".join(header) + "\n")
        # one %-format per row: a generator of f-strings cost the stream thread 3x as much
        self._row_format = "%.6f,%d,%d," + ",".join(["%.5f"] * (2 * len(channels))) + "\n"
        part_rows = max(MIN_PART_ROWS, round(PART_SECONDS * rate_hz))
        self._parquet = StreamParquet(self.path / "stream", channels, part_rows)

    def stream_row(self, sample: int, move: int, commanded, measured,
                   period_error_s: float | None = None) -> None:
        assert self._stream is not None, "open_stream first"
        t = time.monotonic() - self.t0
        self._stream.write(self._row_format % (t, sample, move, *_floats(commanded),
                                               *_floats(measured)))
        if self._parquet is not None:
            self._parquet.append(t, sample, move, commanded, measured, period_error_s)

    def open_series(self, name: str, columns: list[str], units: dict[str, str]) -> "Series":
        """A side series of the run beside the stream (`series/<name>.csv`, line-buffered, with
        `series/<name>.units.json`): what a sensor measured at its own rate (the Hall board's
        fields and gradients), in the units given per column."""
        folder = self.path / "series"
        folder.mkdir(exist_ok=True)
        (folder / f"{name}.units.json").write_text(json.dumps(units, indent=1))
        series = Series(folder / f"{name}.csv", columns)
        self._series.append(series)
        return series

    def finish(self, summary: dict) -> None:
        self.close()
        self.write_file("summary.json", json.dumps(summary, indent=2, default=_jsonable) + "\n")

    def close(self) -> None:
        for series in self._series:
            series.close()
        if self._parquet is not None:
            self._parquet.close()
            self._parquet = None
        with self._lock:
            for f in (self._events, self._stream):
                if f is not None and not f.closed:
                    f.close()


class Series:
    """One side series: `row(values)` appends a line (thread-safe), flushed as it is written."""

    def __init__(self, path: Path, columns: list[str]) -> None:
        self.columns = list(columns)
        self._lock = threading.Lock()
        self._file: TextIO = open(path, "a", buffering=1)
        self._file.write(",".join(self.columns) + "\n")
        self._format = ",".join(["%.9g"] * len(self.columns)) + "\n"

    def row(self, values: Any) -> None:
        line = self._format % tuple(_floats(values))
        with self._lock:
            if not self._file.closed:
                self._file.write(line)

    def close(self) -> None:
        with self._lock:
            self._file.close()


def read_series(run_dir: str | Path, name: str) -> dict[str, Any] | None:
    """A side series (`RunRecord.open_series`) as arrays keyed by column, plus `units`; None if
    the run has none of that name. A line cut off by a crash is skipped."""
    path = Path(run_dir) / "series" / f"{name}.csv"
    if not path.is_file():
        return None
    header, rows = _read_journal(path)
    data = np.asarray(rows, dtype=float).reshape(-1, len(header))
    out: dict[str, Any] = {c: data[:, j] for j, c in enumerate(header)}
    units_path = path.with_suffix(".units.json")
    out["units"] = json.loads(units_path.read_text()) if units_path.is_file() else {}
    return out


def _floats(values: Any) -> list:
    return values.tolist() if isinstance(values, np.ndarray) else list(values)


def _jsonable(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


# -- reading records -----------------------------------------------------------------------------

def read_events(run_dir: str | Path) -> list[dict]:
    """Every event of the log; a last line cut off by a crash is skipped."""
    events: list[dict] = []
    path = Path(run_dir) / "events.jsonl"
    if not path.is_file():
        return events
    for line in path.read_text().splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            log.warning("%s: skipping a cut-off line", path)
    return events


def _read_journal(path: Path, skip_rows: int = 0) -> tuple[list[str], list[list[float]]]:
    """The header and the rows after the first `skip_rows` (passed over as lines, unparsed: the
    Parquet parts have them; parsing them took 1.6 s of reading a 10-minute record)."""
    rows: list[list[float]] = []
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader, [])
        for _ in itertools.islice(f, skip_rows):
            pass
        for row in reader:
            if len(row) != len(header):
                continue  # cut off by a crash
            try:
                rows.append([float(x) for x in row])
            except ValueError:
                continue
    return header, rows


def read_stream(run_dir: str | Path) -> dict[str, Any] | None:
    """The run's per-cycle series as numpy arrays keyed by column name, plus `channels`
    (`Channel`s), `coils` (their names) and `source`: the Parquet parts, completed from the
    journal when a crash cut the last part off. None when the run never streamed."""
    run_dir = Path(run_dir)
    parts = sorted((run_dir / "stream").glob("part-*.parquet"))
    journal = run_dir / "stream.csv"
    columns: dict[str, np.ndarray] = {}
    channels: list[Channel] = []
    if (run_dir / "channels.json").is_file():
        try:
            channels = channels_from_dicts(json.loads((run_dir / "channels.json").read_text()))
        except (json.JSONDecodeError, TypeError):
            channels = []
    n_parquet = 0
    if parts:
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.concat_tables([pq.read_table(p) for p in parts])
        meta = table.schema.metadata or {}
        if not channels and b"rigctl.core.channels" in meta:
            channels = channels_from_dicts(json.loads(meta[b"rigctl.core.channels"]))
        elif not channels:  # a record from before channels: currents in A
            channels = [Channel(n, "A") for n in json.loads(meta.get(b"rigctl.physics.coils", b"[]"))]
        columns = {name: table.column(name).to_numpy() for name in table.column_names}
        n_parquet = table.num_rows
    source = "parquet"
    if journal.is_file():
        header, rows = _read_journal(journal, skip_rows=n_parquet)
        if not channels:
            channels = [Channel(name, unit) for name, unit in
                        (h[4:].rsplit("_", 1) for h in header if h.startswith("cmd_"))]
        if rows:
            tail = np.asarray(rows, dtype=float)
            source = "journal" if n_parquet == 0 else "parquet+journal"
            for j, name in enumerate(header):
                values = tail[:, j]
                columns[name] = values if name not in columns else np.concatenate(
                    [columns[name], values.astype(columns[name].dtype)])
            if "period_error_s" in columns and len(columns["period_error_s"]) < len(columns["t_s"]):
                missing = len(columns["t_s"]) - len(columns["period_error_s"])
                columns["period_error_s"] = np.concatenate([columns["period_error_s"],
                                                            np.full(missing, np.nan)])
    if not columns:
        return None
    return {**columns, "channels": channels, "coils": [c.name for c in channels],
            "source": source}


def describe_run(run_dir: str | Path, *, last_events: int = 50) -> dict:
    """A run record in brief: id, files, summary (None if it did not finish), the last events."""
    run_dir = Path(run_dir)
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
    events = read_events(run_dir)
    return {
        "id": run_dir.name,
        "path": str(run_dir.resolve()),
        "files": sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()),
        "finished": summary is not None,
        "summary": summary,
        "events": events[-last_events:],
        "n_events": len(events),
    }


def list_runs(root: str | Path, *, limit: int = 20) -> list[dict]:
    """The newest `limit` run records under `root`, newest first."""
    root = Path(root)
    if not root.is_dir():
        return []
    runs = []
    for run_dir in sorted((p for p in root.iterdir() if (p / "events.jsonl").is_file()),
                          key=lambda p: p.name, reverse=True)[:limit]:
        summary_path = run_dir / "summary.json"
        summary = None
        if summary_path.is_file():
            try:
                summary = json.loads(summary_path.read_text())
            except json.JSONDecodeError:
                summary = None
        plan = None
        if (run_dir / "plan.json").is_file():
            try:
                plan = json.loads((run_dir / "plan.json").read_text()).get("name")
            except json.JSONDecodeError:
                plan = None
        runs.append({
            "id": run_dir.name, "plan": plan, "finished": summary is not None,
            "reached": None if summary is None else summary.get("reached"),
            "faults": None if summary is None else summary.get("faults"),
            "duration_s": None if summary is None else summary.get("duration_s"),
        })
    return runs
