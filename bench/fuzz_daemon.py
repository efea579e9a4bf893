"""Benchmark: generated requests, raw frames and plans thrown at a daemon. Prints one JSON object.

The daemon drives the emulated six-coil bench (supplies on real TCP sockets, in this process) with
the real plan runs. `--requests` generated requests and raw frames (wrong types at every field of
every command, unhashable values, nesting thousands deep, integers of thousands of digits, NaN and
infinity, lone surrogates, multipart and empty frames, over MAX_REQUEST_BYTES) and `--plans`
generated plan documents (the examples with one value made extreme: 1e300 mm, infinity, NaN, huge
counts, empty or huge lists, a huge workspace image) each sent as `load` and checked in process by
`rigctl validate`, the function the command line runs. Reports: daemon exits, replies with no
`code`, `internal` replies, plans answered otherwise than ok / `plan_invalid` / `limit` /
`too_large` / `bad_json`, `validate` exits other than 0 and 2 (a traceback), and the worst reply
time of each kind (the issue's goal: zero of each, every reply within 1 s).

    python bench/fuzz_daemon.py                           # 10^5 requests, 10^4 plans
    python bench/fuzz_daemon.py --requests 200 --plans 20 # a smoke run

A line per CHUNK examples on stderr (done, internal so far, elapsed, this process's RSS); `rss_mb`
in the JSON: at the start, the end and the peak.

The strategies are the ones tests/integration/test_daemon_fuzz.py runs in CI with fewer examples.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
import time
import zlib
from pathlib import Path

import zmq
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

from rigctl.apps.daemon.messages import COMMAND_ARGS, MAX_REQUEST_BYTES, Command, ErrorCode

EXAMPLES = Path(__file__).resolve().parents[1] / "plans" / "examples"
PLAN_BASES = ("fig4-quick.json", "pair-formation-change.json", "coilboard-disk.json",
              "depm-plan.json")
REPLY_WAIT_S = 10.0  # how long a probe waits before it counts "no reply"
PLAN_CODES = {"plan_invalid", "limit", "too_large", "bad_json", "busy", "deadline"}

# -- strategies ---------------------------------------------------------------------------------


def _json(value) -> bytes:
    return json.dumps(value, allow_nan=True).encode()  # ASCII: a lone surrogate as \ud800


_scalars = (st.none() | st.booleans() | st.integers() | st.floats()
            | st.text(st.characters(codec=None, min_codepoint=0, max_codepoint=0x10FFFF,
                                    exclude_categories=()), max_size=20))
json_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.text(max_size=5), inner, max_size=4), max_leaves=12)
"""Any JSON value Python can write (NaN and infinity included), lone surrogates in strings."""


@st.composite
def _deep(draw) -> bytes:
    depth = draw(st.integers(10, 200_000))
    if draw(st.booleans()):
        return b"[" * depth + b"]" * depth
    return b'{"a":' * depth + b"1" + b"}" * depth


extreme = st.one_of(
    json_values.map(_json),
    st.integers(20, 6000).map(lambda n: b"9" * n),  # past Python's int-str limit (4300 digits)
    st.sampled_from([b"1e300", b"-1e300", b"1e400", b"NaN", b"Infinity", b"-Infinity", b"-0.0",
                     b'"\\ud800"', b'"\\udfff\\ud800"', b"[]", b"{}", b'""', b"null"]),
    st.builds(lambda v, n: b"[" + b",".join([v] * n) + b"]",
              st.sampled_from([b"1e300", b"[1e300,0]", b"0", b"[0,0]"]), st.integers(0, 50_000)),
    _deep(),
)
"""Raw JSON text of a value a field should not get (or might, at its edge)."""

_FIELDS = {cmd: list(model.model_fields) or ["extra"] for cmd, model in COMMAND_ARGS.items()}


@st.composite
def requests(draw) -> bytes:
    """A request frame with one part replaced by an extreme value: `id`, `cmd`, `args`, or one
    field of one command's arguments (a field it does not have for commands without any)."""
    cmd = draw(st.sampled_from(list(Command)))
    where = draw(st.sampled_from(["id", "cmd", "args", "field", "field", "field"]))
    value = draw(extreme)
    request_id = value if where == "id" else b'"fuzz-0001"'
    name = value if where == "cmd" else _json(cmd.value)
    args = value if where == "args" else b"{}"
    if where == "field":
        args = b"{" + _json(draw(st.sampled_from(_FIELDS[cmd]))) + b":" + value + b"}"
    return b'{"id":' + request_id + b',"cmd":' + name + b',"args":' + args + b"}"


raw_frames = st.one_of(
    st.lists(st.binary(max_size=64), max_size=4),  # multipart, empty, not UTF-8
    st.lists(st.sampled_from([b"", b"{}", b'{"cmd":"ping"}']), min_size=2, max_size=4),
    st.just([b"x" * (MAX_REQUEST_BYTES + 1)]),  # oversize: too_large
    st.just([b""]),
)
"""The frames after a DEALER's empty delimiter (multipart, empty, binary, oversize)."""


def _paths(value, prefix=()):
    """Every path into a JSON document (lists: the first two items and the last)."""
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index in sorted({0, 1, len(value) - 1} & set(range(len(value)))):
            yield from _paths(value[index], (*prefix, index))


def _replaced(document, path, value):
    if not path:
        return value
    copy = list(document) if isinstance(document, list) else dict(document)
    copy[path[0]] = _replaced(document[path[0]], path[1:], value)
    return copy


def huge_png(path: Path, side: int = 4100) -> Path:
    """A white PNG of side x side pixels (a few kB on disk; MAX_IMAGE_PIXELS is 2048^2)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return len(data).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")

    header = side.to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])  # 8-bit grey
    pixels = zlib.compress((b"\x00" + b"\xff" * side) * side, 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels)
                     + chunk(b"IEND", b""))
    return path


def plans(image: Path):
    """Plan documents (as JSON text, NaN allowed): an example with one value made extreme, a
    list emptied or made huge, or an image workspace too large to decode."""
    bases = [json.loads((EXAMPLES / name).read_text()) for name in PLAN_BASES]
    values = st.one_of(
        json_values, st.sampled_from([1e300, -1e300, math.inf, -math.inf, math.nan, 10**20, 0,
                                      -1, [], {}, "", [[1e300, 0.0]], [[0.0, 0.0]]]),
        st.integers(0, 30_000).map(lambda n: [[10.0, 0.0]] * n),
        st.floats(-1e4, 1e4), st.integers(-10, 10_000),  # within the bounds: the checks past them
    )

    @st.composite
    def plan(draw) -> bytes:
        base = draw(st.sampled_from(bases))
        if draw(st.integers(0, 19)) == 0:
            image_ws = {"image": str(image), "mm_per_px": 0.1, "origin": [0, 0]}
            document = {**base, "workspace": image_ws}
        else:
            path = draw(st.sampled_from(list(_paths(base))[1:]))
            document = _replaced(base, path, draw(values))
        return _json(document)

    return plan()


# -- probing a daemon -----------------------------------------------------------------------------


class Probe:
    """Sends frames to the daemon's command socket and waits for the reply (a DEALER, so any
    frames can go out; a new socket after a request that got no reply)."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.context = zmq.Context.instance()
        self.socket = None

    def send(self, frames: list[bytes], wait_s: float = REPLY_WAIT_S) -> tuple[dict | None, float]:
        """(the reply's JSON, or None when none came within wait_s; seconds it took)."""
        if self.socket is None:
            self.socket = self.context.socket(zmq.DEALER)
            self.socket.setsockopt(zmq.LINGER, 0)
            self.socket.connect(self.endpoint)
        started = time.monotonic()
        self.socket.send_multipart([b"", *frames])
        if not self.socket.poll(int(wait_s * 1000)):
            self.close()
            return None, time.monotonic() - started
        reply = self.socket.recv_multipart()
        return json.loads(reply[-1]), time.monotonic() - started

    def close(self) -> None:
        if self.socket is not None:
            self.socket.close()
            self.socket = None


def reply_code(reply: dict | None) -> str | None:
    """"ok", the error code, or None for no reply / a reply without one."""
    if not isinstance(reply, dict):
        return None
    if reply.get("ok") is True:
        return "ok"
    code = (reply.get("error") or {}).get("code")
    return code if code in {c.value for c in ErrorCode} else None


def validate_in_process(text: bytes, folder: Path) -> tuple[int, str]:
    """`rigctl validate` of a plan document, in this process: (exit status, stderr)."""
    from rigctl.apps.cli.main import main

    path = folder / "plan.json"
    path.write_bytes(text)
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        status = main(["validate", str(path)])
    return status, err.getvalue()


@contextlib.contextmanager
def daemon_on_bench(runs_dir: Path):
    """A daemon (the real plan runs, its stream process) on the emulated six-coil bench."""
    from rigctl.apps.daemon.server import Daemon
    from rigctl.emulators.bench import SixCoilBench

    with SixCoilBench() as bench:
        daemon = Daemon(bench.rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
                        events="tcp://127.0.0.1:0", runs_dir=runs_dir)
        daemon.start_thread()
        try:
            yield daemon
        finally:
            daemon.stop()


CHUNK = 2000
"""Examples per hypothesis run. One run keeps what it learnt of every example it drew (to draw no
example twice): generating requests alone took this process from 103 MB (200 examples) to 400 MB
(6000), and the full bench past 960 MB in 21 minutes. In chunks of 2000, each of its own seed,
6000 took it to 200 MB and 16000 to 248 MB (measured, the requests' strategy with no daemon)."""


def exhaust(strategy, n: int, check, label: str, progress) -> None:
    """Run `check` on `n` examples of `strategy` (hypothesis as a generator: no shrinking), in
    chunks of CHUNK with seeds 0, 1, ... (the same examples on every run of the bench), calling
    `progress(label, done, n)` after each."""
    done = 0
    for k in range(math.ceil(max(n, 0) / CHUNK)):
        size = min(CHUNK, n - done)
        run = settings(max_examples=size, deadline=None, database=None,
                       phases=[Phase.generate], suppress_health_check=list(HealthCheck))(
            seed(k)(given(strategy)(check)))
        run()
        done += size
        progress(label, done, n)


def _rss_mb() -> float:
    """This process's resident set (the daemon's threads run in it), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=100_000)
    parser.add_argument("--plans", type=int, default=10_000)
    parser.add_argument("--slowest-to", metavar="DIR",
                        help="write the slowest request and plan load, whole, into DIR")
    args = parser.parse_args()
    import logging

    logging.disable(logging.CRITICAL)  # the daemon logs every refusal; the counts say enough
    counts = {"requests": 0, "raw_frames": 0, "plans": 0, "no_code": 0, "internal": 0,
              "plan_other": 0, "validate_traceback": 0, "validate_other_exit": 0}
    worst = {"request_s": 0.0, "load_s": 0.0, "validate_s": 0.0}
    load_codes: dict[str, int] = {}
    slowest: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp, daemon_on_bench(Path(tmp) / "runs") as daemon:
        probe, folder = Probe(daemon.endpoints.command), Path(tmp)
        image = huge_png(folder / "huge.png")

        def note(kind: str, reply: dict | None, seconds: float, frames: list[bytes]) -> str | None:
            counts[kind] += 1
            key = "load_s" if kind == "plans" else "request_s"
            if seconds > worst[key]:
                worst[key] = seconds
                slowest[key] = f"{sum(map(len, frames))} bytes: {b'|'.join(frames)[:60]!r}"
                if args.slowest_to:  # the whole of it, to replay
                    Path(args.slowest_to).mkdir(parents=True, exist_ok=True)
                    (Path(args.slowest_to) / f"slowest-{key}.bin").write_bytes(b"\n".join(frames))
            code = reply_code(reply)
            counts["no_code"] += code is None
            counts["internal"] += code == "internal"
            return code

        def one_request(payload: bytes) -> None:
            note("requests", *probe.send([payload]), [payload])

        def one_frame_set(frames: list[bytes]) -> None:
            note("raw_frames", *probe.send(frames), frames)

        def one_plan(text: bytes) -> None:
            payload = b'{"id":"fuzz-plan","cmd":"load","args":{"plan":' + text + b"}}"
            code = note("plans", *probe.send([payload]), [payload])
            counts["plan_other"] += code not in PLAN_CODES | {"ok", None, "internal"}
            load_codes[str(code)] = load_codes.get(str(code), 0) + 1
            started = time.monotonic()
            try:
                status, _ = validate_in_process(text, folder)
            except Exception:  # noqa: BLE001 - what is counted: a traceback from validate
                counts["validate_traceback"] += 1
            else:
                counts["validate_other_exit"] += status not in (0, 2)
            worst["validate_s"] = max(worst["validate_s"], time.monotonic() - started)

        started = time.monotonic()
        rss = {"start_mb": round(_rss_mb(), 1)}

        def progress(label: str, done: int, total: int) -> None:
            rss["end_mb"] = round(_rss_mb(), 1)
            rss["peak_mb"] = max(rss.get("peak_mb", 0.0), rss["end_mb"])
            print(f"fuzz: {label} {done}/{total}, {counts['internal']} internal, "
                  f"{counts['no_code']} without a code, {time.monotonic() - started:.0f} s, "
                  f"rss {rss['end_mb']:.0f} MB", file=sys.stderr, flush=True)

        exhaust(requests(), args.requests * 9 // 10, one_request, "requests", progress)
        exhaust(raw_frames, args.requests - args.requests * 9 // 10, one_frame_set, "raw frames",
                progress)
        exhaust(plans(image), args.plans, one_plan, "plans", progress)
        ping, _ = probe.send([b'{"cmd":"ping"}'])
        probe.close()
        alive = daemon._thread is not None and daemon._thread.is_alive()
    print(json.dumps({**counts, "daemon_exits": int(not alive),
                      "ping_after": reply_code(ping) == "ok", "load_codes": load_codes,
                      **{f"worst_{k}": round(v, 4) for k, v in worst.items()},
                      "slowest": slowest, "rss_mb": rss,
                      "seconds": round(time.monotonic() - started, 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
