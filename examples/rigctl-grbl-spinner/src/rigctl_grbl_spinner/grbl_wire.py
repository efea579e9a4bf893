"""GRBL 1.1h's serial protocol in front of `GrblMachine`: bytes in, bytes out, no I/O of its own.

What it does, from gnea/grbl doc/markdown (interface.md, commands.md, jogging.md):

- Real-time bytes are taken out of the stream wherever they arrive, mid-line included, and never
  reach the line buffer: `?` status report, `!` feed hold, `~` cycle start, 0x18 soft reset,
  0x85 jog cancel; the other extended-ASCII bytes (0x84 door, the overrides) are swallowed (the
  spinner has no door or spindle). Two `?` before a report is sent give one report.
- Everything else is a line (LF or CR ends it; spaces and `(...)`/`;` comments dropped, letters
  upper-cased, as GRBL's pre-parser does) in a 128-byte serial RX buffer: bytes beyond it are
  lost, as on the Arduino, so a host must count characters (or wait for each reply). A line longer
  than 80 characters is `error:11`. Every line gets one `ok` or `error:N`, in order: a jog gets
  its `ok` once it is in the planner, so while the planner is full the line waits and the host's
  next `ok` with it.
- `$` help, `$$` settings, `$x=val`, `$I`, `$G`, `$X` unlock, `$J=` jogs (`G20/G21`, `G90/G91`,
  `G53`, axis words and a required `F`; accepted in Idle or Jog only: `error:8` otherwise,
  `error:16` for other words, `error:22` without `F`). Lines of modal words only (`G90`, `G91`,
  `G20`, `G21`, `G94`) are accepted; any other G-code is `error:20` here: the spinner is driven by
  jogs alone (a guess at what matters, not GRBL's full G-code interpreter), and `error:9` in Alarm
  or Jog, as GRBL locks G-code out then.
- Soft reset: `ALARM:3` if it stopped a motion, then the welcome banner, then
  `[MSG:'$H'|'$X' to unlock]` while in alarm; the RX buffer, a waiting line and a pending `?` are
  dropped.
- Status reports: `<State|MPos:x,y,z|FS:feed,speed>` (feed in degrees/min here: the axis is in
  degrees), `|Bf:blocks,bytes` when `$10` asks for it, `|WCO:...` in the first report after a
  reset and then every 10 (moving) or 30 reports, `|Ov:100,100,100` in the second and then every
  10 or 20 (a later one when WCO takes the report), as report.c counts them.
"""

from __future__ import annotations

import re

from rigctl_grbl_spinner.grbl_model import INTEGER_SETTINGS, GrblMachine

VERSION = "1.1h"
BANNER = f"Grbl {VERSION} ['$' for help]"
RX_BUFFER_BYTES = 128
LINE_BYTES = 80  # LINE_BUFFER_SIZE: a longer line is error:11

STATUS, HOLD, RESUME, RESET, JOG_CANCEL = b"?", b"!", b"~", b"\x18", b"\x85"
REALTIME = {STATUS[0], HOLD[0], RESUME[0], RESET[0]}

OK = "ok"
ERR_BAD_NUMBER, ERR_INVALID_STATEMENT, ERR_NEGATIVE = 2, 3, 4
ERR_IDLE, ERR_LOCKED, ERR_OVERFLOW, ERR_JOG = 8, 9, 11, 16
ERR_UNSUPPORTED, ERR_NO_FEED, ERR_NO_AXIS = 20, 22, 26

_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")
_MODAL_ONLY = {"G90", "G91", "G20", "G21", "G94", "G17", "G54"}


def _number(value: float) -> str:
    return f"{value:.3f}"


class GrblWire:
    """The controller's serial side. `receive(data)` takes what the host wrote and returns what
    the controller writes back at once; `poll()` returns what it writes later by itself (the
    `ok` of a line that waited for the planner); `boot()` the power-on banner. The caller steps the
    machine (`machine.step`) before each call."""

    def __init__(self, machine: GrblMachine | None = None) -> None:
        self.machine = machine or GrblMachine()
        self.rx = bytearray()
        self.waiting: str | None = None  # a jog line held until the planner has room
        self.report_asked = False
        self.absolute = True  # G90 / G91, the parser's distance mode
        self.inches = False  # G20 / G21
        self.reports_since_wco = self.reports_since_ov = 0
        self._wco_next = self._ov_next = True  # the first reports after a reset carry them
        self.lost_bytes = 0  # bytes that did not fit in the RX buffer (a host that overran it)
        self.lines = 0

    def boot(self) -> bytes:
        return f"\r\n{BANNER}\r\n".encode()

    # -- the wire -------------------------------------------------------------------------------
    def receive(self, data: bytes) -> bytes:
        out = bytearray()
        for byte in data:
            if byte in REALTIME:
                out += self._realtime(byte)
            elif byte == JOG_CANCEL[0]:
                self.machine.jog_cancel_now()
            elif byte >= 0x80:
                continue  # door and overrides: nothing on a spinner
            elif len(self.rx) < RX_BUFFER_BYTES - 1:
                self.rx.append(byte)
            else:
                self.lost_bytes += 1
        out += self.poll()
        if self.report_asked:
            self.report_asked = False
            out += self.status_report().encode() + b"\r\n"
        return bytes(out)

    def poll(self) -> bytes:
        """Execute the lines the RX buffer holds, as far as the planner lets them."""
        out = []
        while True:
            if self.waiting is not None:
                if self.machine.planner_full:
                    break
                line, self.waiting = self.waiting, None
                out.append(self._jog(line))
                continue
            end = next((i for i, b in enumerate(self.rx) if b in (0x0A, 0x0D)), None)
            if end is None:
                break
            raw = bytes(self.rx[:end]).decode("ascii", errors="replace")
            del self.rx[:end + 1]
            reply = self._line(raw)
            if reply is not None:
                out.append(reply)
        return "".join(f"{line}\r\n" for line in out).encode()

    def _realtime(self, byte: int) -> bytes:
        if byte == STATUS[0]:
            self.report_asked = True
        elif byte == HOLD[0]:
            self.machine.feed_hold()
        elif byte == RESUME[0]:
            self.machine.cycle_start()
        elif byte == RESET[0]:
            return self._reset()
        return b""

    def _reset(self) -> bytes:
        alarm = self.machine.soft_reset()
        self.rx.clear()
        self.waiting = None
        self.report_asked = False
        self.absolute, self.inches = True, False
        self._wco_next = self._ov_next = True
        out = f"ALARM:{3}\r\n" if alarm else ""
        out += f"\r\n{BANNER}\r\n"
        if self.machine.state == "Alarm":
            out += "[MSG:'$H'|'$X' to unlock]\r\n"
        return out.encode()

    # -- lines ----------------------------------------------------------------------------------
    def _line(self, raw: str) -> str | None:
        """One line's reply; None while it waits for room in the planner. An empty line is
        `ok` too, so a host that ends its lines with CR LF gets two replies (send LF only)."""
        line = re.sub(r"\([^)]*\)", "", raw).split(";")[0]
        line = line.replace(" ", "").upper()
        self.lines += 1
        if not line:
            return OK
        if len(line) > LINE_BYTES:
            return f"error:{ERR_OVERFLOW}"
        if line.startswith("$"):
            return self._system(line)
        return self._gcode(line)

    def _system(self, line: str) -> str | None:
        machine = self.machine
        idle = machine.state in ("Idle", "Alarm")
        if line == "$":
            return "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\nok"
        if line == "$X":
            if machine.state == "Alarm":
                machine.unlock()
                return "[MSG:Caution: Unlocked]\r\nok"
            return OK
        if line == "$G":
            modes = f"G0 G54 G17 {'G20' if self.inches else 'G21'} {'G90' if self.absolute else 'G91'}"
            return f"[GC:{modes} G94 M5 M9 T0 F0 S0]\r\nok"
        if line.startswith("$J="):
            if machine.planner_full:
                self.waiting = line
                return None  # its ok comes once there is room
            return self._jog(line)
        if not idle:
            return f"error:{ERR_IDLE}"
        if line == "$$":
            rows = [f"${n}={int(v)}" if n in INTEGER_SETTINGS else f"${n}={_number(v)}"
                    for n, v in sorted(machine.settings.items())]
            return "\r\n".join([*rows, OK])
        if line == "$I":
            return f"[VER:{VERSION}.20190830:]\r\n[OPT:V,15,128]\r\nok"
        match = re.fullmatch(r"\$(\d+)=(.*)", line)
        if match is None:
            return f"error:{ERR_INVALID_STATEMENT}"
        number, text = int(match.group(1)), match.group(2)
        if number not in machine.settings:
            return f"error:{ERR_INVALID_STATEMENT}"
        try:
            value = float(text)
        except ValueError:
            return f"error:{ERR_BAD_NUMBER}"
        if value < 0:
            return f"error:{ERR_NEGATIVE}"
        machine.settings[number] = float(int(value)) if number in INTEGER_SETTINGS else value
        return OK

    def _jog(self, line: str) -> str:
        machine = self.machine
        if machine.state not in ("Idle", "Jog"):  # during a jog cancel: Jog, queued, then flushed
            return f"error:{ERR_IDLE}"
        words = line[3:]
        parsed = _WORD.findall(words)
        if "".join(letter + value for letter, value in parsed) != words:
            return f"error:{ERR_BAD_NUMBER}" if re.search(r"[A-Z](?![-+.\d])", words) else \
                f"error:{ERR_JOG}"
        absolute, scale, feed, target = self.absolute, 25.4 if self.inches else 1.0, None, None
        for letter, value in parsed:
            number = float(value)
            if letter == "G":
                if value in ("90", "91"):
                    absolute = value == "90"
                elif value in ("20", "21"):
                    scale = 25.4 if value == "20" else 1.0
                elif value != "53":
                    return f"error:{ERR_JOG}"
            elif letter == "F":
                feed = number
            elif letter == "X":
                target = number
            elif letter not in "YZ":  # the other axes exist on the controller; nothing turns them
                return f"error:{ERR_JOG}"
        if feed is None or feed <= 0:
            return f"error:{ERR_NO_FEED}"
        if target is None and not re.search(r"[YZ]", words):
            return f"error:{ERR_NO_AXIS}"
        if target is not None:
            queued_end = machine.position_deg + sum(b.remaining_deg for b in machine.queue)
            delta = target * scale if not absolute else target * scale - queued_end
            machine.jog(delta, feed * scale)
        return OK

    def _gcode(self, line: str) -> str:
        if self.machine.state in ("Alarm", "Jog"):
            return f"error:{ERR_LOCKED}"
        words = re.findall(r"G\d+", line)
        if "".join(words) != line or not set(words) <= _MODAL_ONLY:
            return f"error:{ERR_UNSUPPORTED}"
        for word in words:
            if word in ("G90", "G91"):
                self.absolute = word == "G90"
            elif word in ("G20", "G21"):
                self.inches = word == "G20"
        return OK

    # -- status ---------------------------------------------------------------------------------
    def status_report(self) -> str:
        machine = self.machine
        mask = int(machine.settings.get(10, 1))
        position = f"{_number(machine.machine_position_deg())},0.000,0.000"
        fields = [machine.status_state(), f"{'MPos' if mask & 1 else 'WPos'}:{position}"]
        if mask & 2:
            fields.append(f"Bf:{15 - len(machine.queue)},{RX_BUFFER_BYTES - len(self.rx)}")
        fields.append(f"FS:{round(machine.speed_deg_s * 60.0)},0")
        busy = machine.moving or machine.state in ("Run", "Jog", "Hold")
        self.reports_since_wco += 1
        self.reports_since_ov += 1
        if self._wco_next or self.reports_since_wco >= (10 if busy else 30):
            fields.append("WCO:0.000,0.000,0.000")
            self._wco_next, self.reports_since_wco = False, 0
        elif self._ov_next or self.reports_since_ov >= (10 if busy else 20):
            fields.append("Ov:100,100,100")
            self._ov_next, self.reports_since_ov = False, 0
        return "<" + "|".join(fields) + ">"
