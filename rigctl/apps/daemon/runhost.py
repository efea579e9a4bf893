"""The stream process: where the daemon's plan runs stream, apart from the process that serves clients.

Why a process of its own. A run's stream thread does Python work a thousand times a second (the
sequencer, six supply exchanges, the record, the callbacks) and gives the GIL up at every socket
call. A command thread in the same interpreter then has to win the GIL back at each of its own
socket calls, and under that ping-pong a `status` round trip reached 1-1.5 ms at p99 on two cores.
In its own process the stream shares its GIL with nothing of the daemon's: not the command
thread, not the worker that realizes and allocates the next plan, not the telemetry publisher. It
also makes a crash of the stream side survivable: the daemon sees the pipe close, zeroes every
supply over fresh connections, writes the fault into the run's event log, and keeps serving.

The host process is spawned when the daemon starts (its imports take about a second, which an
`execute` should not wait for) and runs plans one at a time; when it dies, the next run spawns
another. `RemoteRun` is what the daemon holds: it has the `Run` interface (`execute`, `pause`,
`resume`, `abort`, `estop`, `plan`, `record`) and forwards each call. A manual hold is a run like
any plan's (a `rigctl.run.hold.HoldPlan`), whose program also takes `retarget` and `release`.

Messages are pickled tuples over one-way pipes (`multiprocessing.connection.Connection`):

    daemon -> host   ("run", plan, rig, runs_dir, winding_start_C)   ("pause", immediate)
                     ("resume",)  ("abort",)  ("estop", asked_at)  ("event", name, fields)
                     ("retarget", target, setpoints, ramp_s)  ("release", ramp_s)  (a hold's)
                     ("steer", input or None)  ("end",)  (a teleoperation session's)
                     ("exit",)
    host -> daemon   ("ready", pid)   ("cycles", rows): (n, 4 + 2 k) rows of `CycleBatch.row`,
                      t on `time.monotonic()`
                     ("frame", jpeg_b64, width, height, t_source, t_source_unix, positions_mm,
                      tracked_px, lost, frame) (`_FrameTap`)
                     ("winding", t, temperatures_C, state) (the run's live winding model, 10 Hz)
                     ("state", state, info, record_path, record_t0)
                     ("done", summary)   ("failed", kind, message)   ("log", level, name, text)
    host -> daemon   (asked_at, unreached), the e-stop's answer, on a pipe of its own that the
                     daemon's command thread reads itself

Times are `time.monotonic()`, one clock for both processes on Linux, so `asked_at` (when the
daemon took the e-stop) is measured against the host's own clock in the run record.

Inside the host, the stream thread never writes to the pipe: its cycles and state changes go into
a queue that an uplink thread sends in batches (`UPLINK_BATCH_S`), so a daemon slow to read can
delay telemetry but never a cycle. The host's main thread reads the daemon's commands; an e-stop
is carried out there the moment it arrives (`Run.estop` writes zero to every supply from the
calling thread) and acknowledged with the supplies it could not reach.
"""

from __future__ import annotations

import base64
import gc
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, cast

import numpy as np

from rigctl.apps.daemon.telemetry import CycleBatch, WindingEstimate
from rigctl.core import errors
from rigctl.core.config import RigConfig
from rigctl.core.errors import RigError
from rigctl.core.priority import favour

log = logging.getLogger("rigctl.apps.daemon.runhost")  # also when run as `python -m rigctl.apps.daemon.runhost`

FRAME_HZ = 15.0  # camera frames passed on to the daemon (its console) at most this often
FRAME_MAX_WIDTH = 640  # px; a wider frame is scaled down before it is encoded
FRAME_JPEG_QUALITY = 70
UPLINK_BATCH_S = 0.02  # the host sends cycles to the daemon at most this late
UPLINK_MAX_QUEUED = 60_000  # cycles held for a daemon that stopped reading (a minute at 1 kHz)
ESTOP_ACK_S = 0.25  # an e-stop the host has not acknowledged by then: kill it, zero directly
WATCHDOG_POLL_S = 0.1  # how often the daemon checks that a streaming run still reports
SILENCE_MIN_S = 1.0  # a streaming run silent this long (at least; see RemoteRun) is hung
START_TIMEOUT_S = 60.0  # imports on a loaded machine


class HostGone(RigError):
    """The stream process is not running (it crashed, or the daemon is shutting down)."""


TERMINAL_STATES = {"done", "aborted", "faulted", "estopped"}  # RunState values that end a stream


def build_run(plan: Any, rig: RigConfig, *, runs_dir: str | Path, on_cycle: Any = None,
              on_state: Any = None, on_frame: Any = None, **windings: Any) -> Any:
    """The engine's run of `plan` on `rig`, prepared (a plan the rig cannot run is refused here,
    before any I/O), closed loop whenever the rig has a camera, as `rigctl execute` does. Used by
    the daemon to check a plan at load and by the stream process to run it (`windings`: the
    engine's `on_winding` and `winding_start_C`)."""
    from rigctl.rigs import rig_kind

    builder = rig_kind(rig.rig.kind).builder(plan.kind)
    frames = {"on_frame": on_frame} if on_frame is not None else {}  # the console's camera view
    return builder(plan, rig, runs_dir=runs_dir, progress_out=None, on_cycle=on_cycle,
                   on_state=on_state, **frames, **windings)


# -- the daemon's side ----------------------------------------------------------------------------

class RunHost:
    """The stream process and the thread that reads what it sends. Thread-safe. `windings` (a
    rig whose coils heat) takes each run's live estimate, and gives each run its start."""

    def __init__(self, realtime_priority: int | None = None, on_frame: Any = None,
                 windings: WindingEstimate | None = None) -> None:
        self.realtime_priority = realtime_priority
        self.on_frame = on_frame  # a "frame" message's fields (`_FrameTap`)
        self.windings = windings
        self._lock = threading.Lock()  # one sender at a time on the pipe; the process handles
        self._process: Any = None
        self._down: Any = None
        self._acks: Any = None  # e-stop acknowledgements, read by whoever sent the e-stop
        self._ready = threading.Event()
        self._current: RemoteRun | None = None
        self._closing = False

    def start(self) -> None:
        """Spawn the process now (it imports in the background; `submit` waits for it)."""
        with self._lock:
            if self._process is None or self._process.poll() is not None:
                self._spawn()

    def _spawn(self) -> None:
        # a plain `python -m rigctl.apps.daemon.runhost` with the pipes' ends passed down, not
        # multiprocessing's spawn, which imports the parent's main module again in the child
        # (a script embedding the daemon without an `if __name__ == "__main__"` guard would
        # start itself over)
        down_read, down_write = os.pipe()
        up_read, up_write = os.pipe()
        ack_read, ack_write = os.pipe()
        process = subprocess.Popen(
            [sys.executable, "-m", "rigctl.apps.daemon.runhost", str(down_read), str(up_write),
             str(ack_write), str(self.realtime_priority or 0),
             *(["frames"] if self.on_frame is not None else [])],
            pass_fds=(down_read, up_write, ack_write), stdin=subprocess.DEVNULL,
            # a session of its own: a terminal's Ctrl-C (to the whole foreground group) reaches
            # the daemon, which ramps the run down through this process and then ends it
            # (`close`); were it in the group, one arriving before it ignores SIGINT (its imports)
            # would kill it mid-run. Its pipe from the daemon closing also ends it.
            start_new_session=True)
        for fd in (down_read, up_write, ack_write):
            os.close(fd)
        self._process, self._down = process, Connection(down_write, readable=False)
        self._acks = Connection(ack_read, writable=False)
        ready = self._ready = threading.Event()
        threading.Thread(target=self._read, args=(process, Connection(up_read, writable=False),
                                                  ready),
                         name="runhost-reader", daemon=True).start()
        log.info("stream process %d started", process.pid)

    def submit(self, run: RemoteRun) -> None:
        """Hand `run` to the process (spawned again if it died) and return at once."""
        with self._lock:
            if self._closing:
                raise HostGone("the daemon is shutting down")
            if self._process is None or self._process.poll() is not None:
                self._spawn()
            ready = self._ready
        if not ready.wait(START_TIMEOUT_S):
            raise HostGone(f"the stream process did not start within {START_TIMEOUT_S:g} s")
        with self._lock:
            if self._current is not None:
                raise HostGone("the stream process is still running another plan")
            if self._down is None:
                raise HostGone("the stream process exited as it started: see the daemon's log")
            self._current = run
        start = None if self.windings is None else self.windings.start_C()
        try:
            self.send(*run.job, start)  # the windings as warm as the last run left them
        except HostGone:
            with self._lock:
                if self._current is run:
                    self._current = None
            raise
        run._sent()

    def forget_lost(self, timeout_s: float = 5.0) -> None:
        """Wait until a process found gone has been reaped by its reader (the next `submit`
        then spawns a new one); a process that lingers with its pipe broken is killed."""
        with self._lock:
            process = self._process
        if process is None:
            return
        if process.poll() is None:
            process.kill()
        deadline = time.monotonic() + timeout_s
        while self._process is process and time.monotonic() < deadline:
            time.sleep(0.01)

    def send(self, *message: Any) -> None:
        with self._lock:
            if self._down is None:
                raise HostGone("the stream process is not running")
            try:
                self._down.send(message)
            except (OSError, ValueError) as err:
                raise HostGone(f"the stream process is gone ({err})") from None

    def estop_ack(self, asked_at: float, timeout_s: float) -> list[str] | None:
        """The stream process's answer to the e-stop asked at `asked_at`: the supplies it could
        not reach; None if none came within `timeout_s`. Read on the calling thread (the
        daemon's command thread), not the reader, so the reply waits for no other thread."""
        acks = self._acks
        deadline = time.monotonic() + timeout_s
        try:
            while acks is not None and acks.poll(max(0.0, deadline - time.monotonic())):
                token, unreached = acks.recv()
                if token == asked_at:
                    return cast("list[str] | None", unreached)  # (an older e-stop's late answer is passed over)
        except (EOFError, OSError):
            pass
        return None

    def kill(self) -> None:
        """For a host that stopped answering: SIGKILL (its reader then reports the loss)."""
        process = self._process
        if process is not None and process.poll() is None:
            log.error("stream process %d is not answering: killing it", process.pid)
            process.kill()

    def close(self, timeout_s: float = 30.0) -> None:
        """Ask the process to ramp down whatever it runs and exit; kill it if it will not."""
        with self._lock:
            self._closing = True
            process = self._process
        if process is None:
            return
        try:
            self.send("exit")
        except HostGone:
            pass
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def _watch(self) -> None:
        """The link's watchdog: a run that streams sends cycles every 20 ms; one silent for
        `RemoteRun.silence_limit_s` has a hung stream process (a stuck call, a SIGSTOP). It is
        killed; its pipe then closes and the run ends as if it had crashed: every supply zeroed
        over new connections, a fault recorded."""
        run = self._current
        if run is not None and run._silent_for() > run.silence_limit_s:
            log.error("the stream process has sent nothing for %.1f s while streaming",
                      run._silent_for())
            run.hung = True
            self.kill()

    def _read(self, process: Any, up: Any, ready: threading.Event) -> None:
        try:
            while True:
                if not up.poll(WATCHDOG_POLL_S):
                    self._watch()
                    continue
                message = up.recv()
                kind = message[0]
                if kind == "ready":
                    ready.set()
                elif kind == "log":
                    _, level, name, text = message
                    logging.getLogger(name).log(level, "%s", text)
                else:
                    run = self._current
                    if run is None:
                        continue
                    if kind in ("done", "failed"):
                        with self._lock:
                            self._current = None
                    try:
                        run._receive(message)
                    except Exception:  # a bug in a callback must not pass for a dead process
                        log.exception("handling %r from the stream process failed", kind)
        except (EOFError, OSError):
            pass
        finally:
            ready.set()  # a `submit` waiting for a process that died starting finds it gone
            up.close()
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:  # its pipe closed but it lingers: it is lost anyway
                process.kill()
                process.wait(5)
            with self._lock:
                if self._process is process:
                    self._down.close()
                    self._acks.close()
                    self._process, self._down, self._acks = None, None, None
                run, self._current = self._current, None
            if run is not None:
                run._host_lost(process.returncode)
            elif not self._closing:
                log.warning("stream process %d exited (code %s); the next run starts another",
                            process.pid, process.returncode)


def device_patience_s(rig: RigConfig) -> float:
    """The longest a healthy stream cycle may wait on the rig's own devices before the run itself
    faults: `[stream] reply_timeout_s`, or longer where its kind says its devices may take longer
    (`RigKind.patience_s`: the coil board's retries and reconnect, the arms' reply timeout). A
    stream process silent for twice this is hung."""
    from rigctl.rigs import rig_kind

    return float(max(rig.stream.reply_timeout_s, rig_kind(rig.rig.kind).patience_s(rig)))


class _RecordView:
    """The run record as the daemon sees it: where it is, and events appended by the host."""

    def __init__(self, path: str, t0: float, host: RunHost) -> None:
        self.path = Path(path)
        self.t0 = t0
        self._host = host

    def event(self, event: str, **fields: Any) -> None:
        try:
            self._host.send("event", event, fields)
        except HostGone:
            pass


class RemoteRun:
    """A run streamed by the `RunHost` (`job` ("run", prepared plan, rig, runs dir), see
    `build_run`), with the interface of the run it stands for; a manual hold's also takes
    `retarget` and `release`."""

    def __init__(self, host: RunHost, job: tuple[Any, ...], rig: RigConfig, *, plan: Any, info: dict[str, Any],
                 on_cycles: Any, on_state: Any) -> None:
        self._host = host
        self.job = job  # the message that starts it in the host
        self.plan, self.rig, self.info = plan, rig, info
        self.on_cycles, self.on_state = on_cycles, on_state
        self.started = threading.Event()  # its first cycles came, or it ended without any
        self.streaming = False
        self.record: _RecordView | None = None
        # streaming: cycles come every UPLINK_BATCH_S; longer than a supply's own reply timeout
        # (which the run itself turns into a fault) plus the ramp down, and it is hung
        self.silence_limit_s = max(SILENCE_MIN_S, 2.0 * device_patience_s(rig)
                                   + self.rig.stream.ramp_down_s)
        self._last_cycles: float | None = None  # when cycles last came; None when not streaming
        self.hung = False
        self._done = threading.Event()
        self._result: Any = None
        self._error: Exception | None = None
        self._lock = threading.Lock()
        self._submitted = False
        self._early: list[tuple[Any, ...]] = []  # control calls made before the host had the run
        self._stop_asked = False  # an abort or e-stop was asked: a lost run is not started again

    @property
    def error(self) -> Exception | None:
        return self._error

    def execute(self) -> Any:
        for attempt in (1, 2):
            try:
                self._host.submit(self)
            except HostGone as err:
                self._error = err
            else:
                self._done.wait()
            if not (attempt == 1 and isinstance(self._error, HostGone) and self.record is None
                    and not self._stop_asked):
                break
            # the process died before the run began (no record yet: nothing was energised), a
            # process killed while idle, say: once more on a new one
            log.warning("the stream process was lost before the run began (%s); starting the "
                        "run on a new one", self._error)
            self._error, self._submitted, self.hung = None, False, False
            self._done.clear()
            self.started.clear()
            self._host.forget_lost()
        if self._error is not None:
            raise self._error
        return self._result

    @property
    def result(self) -> Any:
        """The run's summary once it ended (None before, or if it failed)."""
        return self._result

    def retarget(self, target: dict[str, Any], setpoints: np.ndarray, ramp_s: float) -> None:
        """A manual hold's new target (`rigctl.run.hold.HoldProgram.retarget`)."""
        self._control("retarget", target, np.asarray(setpoints, dtype=float).tolist(), ramp_s)

    def release(self, ramp_s: float) -> None:
        """A manual hold: ramp to the rig's rest, then end."""
        self._control("release", ramp_s)

    def steer(self, values: list[float] | None) -> None:
        """A teleoperation session's input (`rigctl.run.teleop.TeleopProgram.steer`)."""
        self._control("steer", values)

    def end(self) -> None:
        """A teleoperation session: let go, to rest, then end."""
        self._control("end")

    def pause(self, immediate: bool = False) -> None:
        self._control("pause", immediate)

    def resume(self) -> None:
        self._control("resume")

    def abort(self) -> None:
        self._stop_asked = True
        self._control("abort")

    def estop(self) -> list[str]:
        """Tell the host (which zeroes every supply on receipt) and wait for its answer; a host
        that does not answer within ESTOP_ACK_S is killed and the supplies are zeroed from here.
        Before the host has the run, nothing is energised: the e-stop goes with the run, which
        then never switches on."""
        asked = time.monotonic()
        self._stop_asked = True
        try:
            if not self._control("estop", asked):
                return []
        except HostGone:
            unreached = None
        else:
            unreached = self._host.estop_ack(asked, ESTOP_ACK_S)
        if unreached is None:
            from rigctl.rigs import rig_kind

            self._host.kill()
            unreached = [name for name, err in rig_kind(self.rig.rig.kind).make_safe(self.rig).items()
                         if err]
        return unreached

    def _control(self, *message: Any) -> bool:
        """Send a control message; before the run is with the host, keep it for `_sent`."""
        with self._lock:
            if not self._submitted:
                self._early.append(message)
                return False
        self._host.send(*message)
        return True

    def _sent(self) -> None:
        """The host has the run: what was asked meanwhile follows it, in order."""
        with self._lock:
            for message in self._early:
                self._host.send(*message)
            self._early, self._submitted = [], True

    # called on the host's reader thread
    def _receive(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "cycles":
            self._last_cycles = time.monotonic()
            self.streaming = True
            self.started.set()
            self.on_cycles(CycleBatch.from_rows(message[1]))
        elif kind == "stream_over":  # no more cycles: the watch on them ends (`_silent_for`)
            self._last_cycles = None
        elif kind == "state":
            _, state, info, path, t0 = message
            if self.record is None and path is not None:
                self.record = _RecordView(path, t0, self._host)
            if state.value in TERMINAL_STATES:  # the stream is over: the summary takes its time
                self._last_cycles = None
            self.on_state(state, info)
        elif kind == "winding":
            if self._host.windings is not None:
                self._host.windings.from_run(*message[1:])
        elif kind == "frame":
            if self._host.on_frame is not None:
                self._host.on_frame(*message[1:])
        elif kind == "done":
            self._result = message[1]
            self.started.set()
            self._done.set()
        elif kind == "failed":
            _, name, text, device = message
            error_class = getattr(errors, name, None)
            if isinstance(error_class, type) and issubclass(error_class, RigError):
                self._error = error_class(text, device=device)  # as the device said it
            else:
                self._error = RigError(f"the stream process failed: {name}: {text}")
            self.started.set()
            self._done.set()

    def _silent_for(self) -> float:
        """Seconds since the last cycles while streaming (0 when not streaming)."""
        last = self._last_cycles
        return 0.0 if last is None else time.monotonic() - last

    def _host_lost(self, exitcode: int | None) -> None:
        """The process died with this run on it: make the supplies safe, say so, end the run."""
        from rigctl.rigs import rig_kind

        zeroed = rig_kind(self.rig.rig.kind).make_safe(self.rig)
        unreached = [name for name, err in zeroed.items() if err]
        what = ("stopped answering while streaming and was killed" if self.hung
                else f"died (exit code {exitcode})")
        reason = (f"the stream process {what} during the run; every device "
                  + (f"but {', '.join(unreached)} " if unreached else "")
                  + "was made safe over a new connection")
        log.error("%s", reason)
        if self.record is not None:
            line = {"t": round(time.monotonic() - self.record.t0, 6), "event": "fault",
                    "device": None, "reason": reason, "kind": "StreamProcessDied"}
            with open(self.record.path / "events.jsonl", "a") as events:
                events.write(json.dumps(line) + "\n")
        self._error = HostGone(reason)
        self.started.set()
        self._done.set()


# -- the stream process's side --------------------------------------------------------------------

class _Uplink:
    """The host's sender: queued cycles and messages, sent in order by one thread."""

    def __init__(self, up: Any) -> None:
        self._up = up
        self._lock = threading.Lock()
        self._queue: deque[Any] = deque(maxlen=UPLINK_MAX_QUEUED)
        self._wake = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._serve, name="runhost-uplink", daemon=True)
        self._thread.start()

    def cycle(self, sample: int, move: int, commanded: np.ndarray, measured: np.ndarray,
              error: float | None) -> None:
        """From the stream thread: a deque append, nothing else."""
        self._queue.append(CycleBatch.row(time.monotonic(), sample, move, commanded, measured,
                                          error))

    def message(self, *message: Any) -> None:
        """In order with the cycles before it; sent at once."""
        self._queue.append(message)
        self._wake.set()

    def flush(self) -> None:
        batch: list[Any] = []
        while self._queue:
            item = self._queue.popleft()
            if isinstance(item[0], str):
                self._send_cycles(batch)
                batch = []
                self._send(item)
            else:
                batch.append(item)
        self._send_cycles(batch)

    def close(self) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join(5)
        try:
            self.flush()
        except (OSError, ValueError):  # the daemon went first: nobody to tell
            pass

    def _serve(self) -> None:
        while not self._stop:
            self._wake.wait(UPLINK_BATCH_S)
            self._wake.clear()
            try:
                self.flush()
            except (OSError, ValueError):  # the daemon is gone; the main thread sees it too
                return

    def _send_cycles(self, batch: list[Any]) -> None:
        if batch:
            self._send(("cycles", np.array(batch)))

    def _send(self, message: tuple[Any, ...]) -> None:
        with self._lock:
            self._up.send(message)


class _FrameTap:
    """Camera frames for the daemon's console, off the tracking thread's path: `offer` (from the
    tracking thread) keeps only the newest frame, at most FRAME_HZ a second; a thread of its own
    scales it to FRAME_MAX_WIDTH, encodes it as JPEG (OpenCV releases the GIL meanwhile) and
    sends it up, base64 and all, with what the tracker saw in it, in mm and in the camera's pixels
    (the run's calibration), so that the daemon and its console only pass it on. A frame not yet
    sent when a newer one comes is replaced, so a slow encoder costs frames, never memory or the
    stream's time."""

    def __init__(self, uplink: _Uplink) -> None:
        self.uplink = uplink
        self.calibration: Any = None  # the running rig's camera calibration (set per run)
        self._cond = threading.Condition()
        self._latest: tuple[Any, ...] | None = None
        self._last_t = -float("inf")
        self._thread = threading.Thread(target=self._serve, name="runhost-frames", daemon=True)
        self._thread.start()

    def offer(self, image: np.ndarray, state: Any) -> None:
        now = time.monotonic()
        if now - self._last_t < 1.0 / FRAME_HZ:
            return
        self._last_t = now
        with self._cond:
            self._latest = (image, state)
            self._cond.notify()

    def _serve(self) -> None:
        import cv2

        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._latest is not None)
                latest, self._latest = self._latest, None
            assert latest is not None  # waited for
            image, state = latest
            height, width = image.shape[:2]
            if width > FRAME_MAX_WIDTH:
                scale = FRAME_MAX_WIDTH / width
                image = cv2.resize(image, (FRAME_MAX_WIDTH, round(height * scale)),
                                   interpolation=cv2.INTER_AREA)
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, FRAME_JPEG_QUALITY])
            if not ok:
                continue
            positions = np.asarray(state.positions_mm, dtype=float)
            calibration = self.calibration
            pixels = calibration.to_px(positions).round(1).tolist() if calibration else []
            t_source = float(state.t_source)
            # the capture time on the wall clock too: a browser on this machine reads that clock
            t_source_unix = time.time() - (time.monotonic() - t_source)
            self.uplink.message("frame", base64.b64encode(jpeg.tobytes()).decode("ascii"), width,
                                height, t_source, round(t_source_unix, 6),
                                positions.round(4).tolist(), pixels,
                                [bool(x) for x in state.lost], int(state.frame))


class _ForwardLogs(logging.Handler):
    def __init__(self, uplink: _Uplink) -> None:
        super().__init__(logging.INFO)
        self.uplink = uplink

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            self.uplink.message("log", record.levelno, record.name, text)
        except Exception:
            self.handleError(record)


class _Host:
    """The stream process: one run at a time on its run thread; commands on the main thread."""

    def __init__(self, uplink: _Uplink, acks: Any, realtime_priority: int | None,
                 frames: bool = False) -> None:
        self.uplink = uplink
        self.frames = _FrameTap(uplink) if frames else None  # only for a daemon with a console
        self.acks = acks
        self.realtime_priority = realtime_priority
        self._lock = threading.Lock()
        self.run: Any = None
        self._pending: list[tuple[str, tuple[Any, ...]]] = []  # calls made while the Run was being built
        self._thread: threading.Thread | None = None

    def serve(self, down: Any) -> None:
        while True:
            try:
                message = down.recv()
            except (EOFError, OSError):  # the daemon died: ramp down, as on shutdown
                log.error("the daemon went away: ramping down")
                self._call("abort")
                break
            kind, args = message[0], message[1:]
            if kind == "run":
                self._start(self._build_run, *args)
            elif kind == "estop":
                unreached = self._call("estop", *args)
                self.acks.send((args[0], unreached or []))  # the daemon waits for this
            elif kind == "event":
                name, fields = args
                run = self.run
                if run is not None and run.record is not None:
                    run.record.event(name, **fields)
            elif kind == "exit":
                self._call("abort")
                break
            else:
                try:
                    self._call(kind, *args)
                except RigError as err:  # the daemon refuses what a run refuses: a bug if here
                    log.error("%s refused by the run: %s", kind, err)
        if self._thread is not None:
            self._thread.join()

    def _call(self, name: str, *args: Any) -> Any:
        with self._lock:
            if self.run is None:
                if self._thread is not None and self._thread.is_alive():
                    self._pending.append((name, args))
                return None
            run = self.run
        return _apply(run, name, args)

    def _start(self, build: Any, *args: Any) -> None:
        with self._lock:
            self._pending = []
        self._thread = threading.Thread(target=self._execute, args=(build, *args), name="stream",
                                        daemon=True)
        self._thread.start()

    def _build_run(self, plan: Any, rig: RigConfig, runs_dir: str,
                   winding_start_C: list[float] | None = None) -> Any:
        if self.frames is not None:
            self.frames.calibration = rig.camera.calibration if rig.camera is not None else None
        run: Any = build_run(  # (typed here: the callbacks below name it)
            plan, rig, runs_dir=runs_dir,
            on_cycle=lambda k, move, cmd, meas: self.uplink.cycle(
                k, move, cmd, meas, run.stream_loop.last_error_s),
            on_state=lambda state, info: self.uplink.message(
                "state", state, info, str(run.record.path) if run.record else None,
                run.record.t0 if run.record else None),
            on_frame=self.frames.offer if self.frames is not None else None,
            on_winding=lambda t, temperatures, state: self.uplink.message(
                "winding", t, temperatures, state),
            winding_start_C=winding_start_C)
        # the stream is over: making safe and writing the summary take their time, unwatched
        run.on_stream_end = lambda: self.uplink.message("stream_over")
        return run

    def _execute(self, build: Any, *args: Any) -> None:
        self._stream(build, *args)
        # A run is a web of reference cycles (its callbacks hold it), and the stream's frozen heap
        # (`rigctl.core.stream`) hands it to the oldest generation, which CPython collects only once
        # that has grown by a quarter: each ended run's 0.3 MB stayed (`bench/soak.py`: the
        # stream process grew 437 MB an hour). Collected here, with the run over and its frame
        # gone, where a full collection's 50-70 ms delays no cycle and no e-stop.
        gc.collect()

    def _stream(self, build: Any, *args: Any) -> None:
        try:
            if self.realtime_priority:
                make_realtime(self.realtime_priority)
            run = build(*args)
            with self._lock:
                self.run, pending, self._pending = run, self._pending, []
            for name, pending_args in pending:  # an e-stop before it began: it never energises
                _apply(run, name, pending_args)
            summary = run.execute()
            self.uplink.message("done", summary)
        except BaseException as err:  # reported to the daemon, which faults the run
            log.exception("the stream job failed")
            text = err.args[0] if isinstance(err, RigError) and err.args else str(err)
            self.uplink.message("failed", type(err).__name__, text, getattr(err, "device", None))
        finally:
            with self._lock:
                self.run = None


PROGRAM_CALLS = {"retarget", "release", "steer", "end"}  # a hold's, a teleoperation's: on its program


def _apply(run: Any, name: str, args: tuple[Any, ...]) -> Any:
    return getattr(run.program if name in PROGRAM_CALLS else run, name)(*args)


def host_main(down: Any, up: Any, acks: Any, realtime_priority: int | None,
              frames: bool = False) -> None:
    """The stream process's entry point (spawned by `RunHost`)."""
    sys.setswitchinterval(1e-4)  # the e-stop on the main thread gets the GIL within 0.1 ms
    favour("stream process", pass_on=True)  # before its threads start: they inherit it (rigctl.core.priority)
    # the daemon decides when to stop: a SIGTERM to the service's whole cgroup or a Ctrl-C to the
    # terminal's process group must not end a run here without its ramp-down (the daemon sends
    # "exit", which ramps down; if the daemon itself dies, its pipe closes and we ramp down too)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    uplink = _Uplink(up)
    root = logging.getLogger()
    root.handlers[:] = [_ForwardLogs(uplink)]
    root.setLevel(logging.INFO)
    host = _Host(uplink, acks, realtime_priority, frames)
    if realtime_priority:  # the e-stop is taken on this thread: ahead of the stream thread
        make_realtime(realtime_priority + 1, "stream process's command thread")
    uplink.message("ready", os.getpid())
    try:
        host.serve(down)
    finally:
        uplink.close()


def make_realtime(priority: int, what: str = "stream thread") -> bool:
    """SCHED_FIFO for the calling thread (Linux applies it per thread), if permitted. Threads and
    processes it starts later do not inherit it (SCHED_RESET_ON_FORK): a worker that realizes a
    plan for seconds must not run at realtime priority because the command thread started it."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(priority))
        log.info("%s at SCHED_FIFO priority %d", what, priority)
        return True
    except (PermissionError, OSError, AttributeError) as err:
        log.warning("realtime scheduling not permitted for the %s (%s): it runs at normal "
                    "priority; allow it with LimitRTPRIO= or CAP_SYS_NICE", what, err)
        return False


def realtime_permitted(priority: int) -> bool:
    """Whether this process may put a thread at SCHED_FIFO `priority` (tried on a thread that
    ends at once, so no thread of ours changes)."""
    result: list[bool] = []

    def attempt() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            result.append(True)
        except (PermissionError, OSError, AttributeError):
            result.append(False)

    probe = threading.Thread(target=attempt, name="realtime-probe")
    probe.start()
    probe.join()
    return result[0]


if __name__ == "__main__":  # python -m rigctl.apps.daemon.runhost DOWN_FD UP_FD ACK_FD PRIORITY [frames]
    host_main(Connection(int(sys.argv[1]), writable=False),
              Connection(int(sys.argv[2]), readable=False),
              Connection(int(sys.argv[3]), readable=False), int(sys.argv[4]) or None,
              frames=sys.argv[5:6] == ["frames"])
