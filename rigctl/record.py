"""The run record: a directory written as the run goes, so a crash loses nothing before the crash.

Layout of `runs/<UTC time>-<plan name>/`:
- `plan.json`: the plan as executed (with `expected` filled);
- `rig.toml`: the rig configuration snapshot;
- `events.jsonl`: append-only event log, one JSON object per line, `{"t": s since start, "event": ...}`;
- `stream.csv`: one line per stream cycle: t, sample index, move index, commanded and measured currents;
- `summary.json`: written last; its absence means the run did not finish.

Every line is flushed when written (line-buffered files): at 1 kHz that is a few microseconds per
cycle, a price worth paying for a record that survives a crash.
"""

from __future__ import annotations

import json
import logging
import re
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, TextIO

log = logging.getLogger(__name__)


class RunRecord:
    def __init__(self, root: str | Path, plan_name: str) -> None:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        safe_name = re.sub(r"[^A-Za-z0-9_.-]+", "-", plan_name).strip("-") or "plan"
        self.path = Path(root) / f"{stamp}-{safe_name}"
        self.path.mkdir(parents=True, exist_ok=False)
        self._t0 = time.monotonic()
        self._events: TextIO = open(self.path / "events.jsonl", "a", buffering=1)
        self._stream: TextIO | None = None

    def write_file(self, name: str, text: str) -> None:
        (self.path / name).write_text(text)

    def event(self, event: str, **fields: Any) -> None:
        entry = {"t": round(time.monotonic() - self._t0, 6), "event": event, **fields}
        self._events.write(json.dumps(entry, default=_jsonable) + "\n")

    def open_stream(self, coil_names: list[str]) -> None:
        self._stream = open(self.path / "stream.csv", "a", buffering=1)
        header = ["t_s", "sample", "move"]
        header += [f"cmd_{n}_A" for n in coil_names] + [f"meas_{n}_A" for n in coil_names]
        self._stream.write(",".join(header) + "\n")

    def stream_row(self, sample: int, move: int, commanded, measured) -> None:
        assert self._stream is not None, "open_stream first"
        t = time.monotonic() - self._t0
        values = ",".join(f"{x:.5f}" for x in (*commanded, *measured))
        self._stream.write(f"{t:.6f},{sample},{move},{values}\n")

    def finish(self, summary: dict) -> None:
        self.write_file("summary.json", json.dumps(summary, indent=2, default=_jsonable) + "\n")
        self.close()

    def close(self) -> None:
        for f in (self._events, self._stream):
            if f is not None and not f.closed:
                f.close()


def _jsonable(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)
