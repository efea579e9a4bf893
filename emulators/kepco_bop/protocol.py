"""The Kepco BOP's SCPI dialect, mapped onto `BopCoilModel` (the lewis "interface" layer).

`BopScpi.handle(line)` takes one program message (the line without its terminator) and returns the
response message (without terminator), or None when the message held no query.

Where the behaviour comes from. BOP = Kepco BOP 1KW-MG operator manual (its SCPI chapter and
Appendix B are shared by the BOP-GL 1KW family that includes the 50-20; paragraph numbers are
the MG manual's); GL = BOP-GL 1KW operator manual; BIT 232 / MST 488 / KLP = manuals of other
Kepco SCPI products, used where the BOP manual we could read is silent (marked "guess").

- Message syntax, BOP par. 3.6.4.6-3.6.4.8 and 3.6.6: units of a message are separated by `;`
  (the manual's own example is `VOLT 15;MEAS:VOLT?`); a leading `:` sends the parser back to
  the root; without it, a unit continues from the node of the previous one (`MEAS:VOLT?;CURR?`
  reads both measurements); the terminator is LF (ASCII 10). Keywords are accepted in short
  (upper-case part) or long form, in any letter case; optional nodes (`[SOURce:]`, `[:LEVel]`,
  ...) may be left out. Common commands start with `*` and do not move the parser.
- Numbers, BOP App. B.2: MAXimum / MINimum keywords; magnitudes above 6500.9999 give -120
  "Numeric data error"; responses are in scientific notation (we print e.g. `1.234500E+00`).
  The real parser also truncates mantissas to 4 + 8 digits; we do not emulate that.
- [SOURce:]CURRent beyond the rating posts -222 "Data out of range" (BOP par. B.17).
  In current mode VOLTage sets the voltage limit (BIT 232 Fig. B-9; GL par. 3.3.6: in current
  mode the voltage protect channel limits the output). FUNCtion:MODE VOLT|CURR selects the main
  channel; FUNC:MODE? answering 0 / 1 is the BIT 4886 behaviour as other drivers report it (guess).
- OUTPut[:STATe] ON|OFF|1|0; OUTP? answers 0 or 1 (BOP par. B.14).
- SYSTem:ERRor? answers `code,"message"`, oldest first, `0,"No error"` when empty; 15 entries,
  then -350 (MST 488 par. B.46; guess for the BOP). Over-temperature is the device error
  20101,"OVER TEMPERATURE" (BOP Table B-5 lists 2yy01, yy the unit's place on the master/slave
  bus; yy = 01 for the master is a guess) and sets the device-error bit (value 8) of *ESR? (Table
  B-5); STAT:QUES:COND? / STAT:QUES? report it as bit 3, value 8 (BIT 232 Fig. B-20; guess).
- Error codes for malformed messages are the IEEE 488.2 / SCPI ones Kepco lists (MST 488 Table
  B-6, BOP Table B-5): -102 syntax error, -108 parameter not allowed, -109 missing parameter,
  -113 undefined header (standard SCPI; guess that the BOP uses it for unknown commands),
  -120 numeric data error, -222 data out of range. A command error (-1xx) discards the rest of
  the message (IEEE 488.2 practice; guess for the BOP); execution errors do not.
- *IDN?, *RST, *CLS, *ESR?, *OPC?, *STB?: IEEE 488.2 common commands; the *IDN? fields are a guess.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.emulators.kepco_bop.model import BopCoilModel

log = logging.getLogger(__name__)

DEFAULT_IDN = "KEPCO,BOP 50-20GL,EMULATED,3.05"
MAX_NUMERIC_MAGNITUDE = 6500.9999  # BOP App. B.2

_NRF = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")


class _ScpiError(Exception):
    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


SYNTAX_ERROR = (-102, "Syntax error")
PARAMETER_NOT_ALLOWED = (-108, "Parameter not allowed")
MISSING_PARAMETER = (-109, "Missing parameter")
UNDEFINED_HEADER = (-113, "Undefined header")
NUMERIC_DATA_ERROR = (-120, "Numeric data error")


@dataclass(frozen=True)
class _Keyword:
    short: str
    long: str
    optional: bool

    def matches(self, word: str) -> bool:
        return word == self.short or word == self.long


def _parse_pattern(pattern: str) -> tuple[_Keyword, ...]:
    """'[SOURce] CURRent [LEVel]' -> keywords; the short form is the upper-case part."""
    keywords = []
    for token in pattern.split():
        optional = token.startswith("[")
        name = token.strip("[]")
        short = "".join(c for c in name if c.isupper())
        keywords.append(_Keyword(short=short, long=name.upper(), optional=optional))
    return tuple(keywords)


def _matches(pattern: tuple[_Keyword, ...], words: list[str]) -> bool:
    if not pattern:
        return not words
    head, rest = pattern[0], pattern[1:]
    if words and head.matches(words[0]) and _matches(rest, words[1:]):
        return True
    return head.optional and _matches(rest, words)


@dataclass(frozen=True)
class _Command:
    pattern: tuple[_Keyword, ...]
    write: Callable[[str], None] | None  # receives the parameter text ("" if none)
    query: Callable[[], str] | None


def _number(text: str, *, maximum: float) -> float:
    """An NRf parameter, or MAX / MIN (the most positive / negative allowed value)."""
    word = text.strip().upper()
    if not word:
        raise _ScpiError(*MISSING_PARAMETER)
    if word in ("MAX", "MAXIMUM"):
        return maximum
    if word in ("MIN", "MINIMUM"):
        return -maximum
    if not _NRF.fullmatch(word):
        raise _ScpiError(*NUMERIC_DATA_ERROR)
    value = float(word)
    if not math.isfinite(value) or abs(value) > MAX_NUMERIC_MAGNITUDE:
        raise _ScpiError(*NUMERIC_DATA_ERROR)
    return value


def _boolean(text: str) -> bool:
    word = text.strip().upper()
    if not word:
        raise _ScpiError(*MISSING_PARAMETER)
    if word in ("ON", "1"):
        return True
    if word in ("OFF", "0"):
        return False
    raise _ScpiError(*SYNTAX_ERROR)


def _scientific(value: float) -> str:
    return f"{value + 0.0:.6E}"


class BopScpi:
    """SCPI command table of one emulated BOP; call `handle` once per received line.

    `before_command` runs once per line before anything is parsed, so a bench can advance the
    whole simulation to "now" and every reply reflects the present.
    """

    def __init__(
        self,
        model: BopCoilModel,
        *,
        before_command: Callable[[], None] = lambda: None,
        idn: str = DEFAULT_IDN,
    ) -> None:
        self.model = model
        self._before_command = before_command
        self._idn = idn
        self._common: dict[str, tuple[Callable[[], None] | None, Callable[[], str] | None]] = {
            "*IDN": (None, lambda: self._idn),
            "*RST": (self.model.reset, None),
            "*CLS": (self.model.clear_status, None),
            "*ESR": (None, lambda: str(self.model.read_event_status())),
            "*OPC": (lambda: None, lambda: "1"),
            "*STB": (None, self._status_byte),
        }
        self._resolved: dict[tuple[str, ...], _Command] = {}
        self._commands = [
            _Command(_parse_pattern("[SOURce] FUNCtion MODE"), self._set_mode,
                     lambda: "1" if self.model.mode == "CURR" else "0"),
            _Command(_parse_pattern("[SOURce] CURRent [LEVel] [IMMediate] [AMPlitude]"),
                     self._set_current, lambda: _scientific(self.model.current_setpoint_A)),
            _Command(_parse_pattern("[SOURce] VOLTage [LEVel] [IMMediate] [AMPlitude]"),
                     self._set_voltage, lambda: _scientific(self.model.voltage_setpoint_V)),
            _Command(_parse_pattern("OUTPut [STATe]"), self._set_output,
                     lambda: "1" if self.model.output_on else "0"),
            _Command(_parse_pattern("MEASure [SCALar] CURRent [DC]"), None,
                     lambda: _scientific(self.model.current_A)),
            _Command(_parse_pattern("MEASure [SCALar] VOLTage [DC]"), None,
                     lambda: _scientific(self.model.voltage_V)),
            _Command(_parse_pattern("SYSTem ERRor [NEXT]"), None, self._next_error),
            _Command(_parse_pattern("STATus QUEStionable CONDition"), None,
                     lambda: str(self.model.questionable_condition())),
            _Command(_parse_pattern("STATus QUEStionable [EVENt]"), None,
                     lambda: str(self.model.read_questionable_event())),
        ]

    # -- command actions ------------------------------------------------------------------------

    def _set_mode(self, text: str) -> None:
        word = text.strip().upper()
        if not word:
            raise _ScpiError(*MISSING_PARAMETER)
        if word in ("CURR", "CURRENT"):
            self.model.set_mode("CURR")
        elif word in ("VOLT", "VOLTAGE"):
            self.model.set_mode("VOLT")
        else:
            raise _ScpiError(*SYNTAX_ERROR)

    def _set_current(self, text: str) -> None:
        self.model.set_current(_number(text, maximum=self.model.current_limit_A))

    def _set_voltage(self, text: str) -> None:
        self.model.set_voltage(_number(text, maximum=self.model.compliance_V))

    def _set_output(self, text: str) -> None:
        self.model.set_output(_boolean(text))

    def _next_error(self) -> str:
        code, message = self.model.pop_error()
        return f'{code},"{message}"'

    def _status_byte(self) -> str:
        # IEEE 488.2: bit 2 = error queue not empty (SCPI), bit 5 = event status summary
        return str((4 if self.model.error_count else 0) | (32 if self.model.event_status else 0))

    # -- parsing --------------------------------------------------------------------------------

    def handle(self, line: str) -> str | None:
        """Execute one program message; the joined query responses, or None if there were none."""
        self._before_command()
        responses: list[str] = []
        path: list[str] = []
        for unit in line.strip().split(";"):
            try:
                path = self._execute(unit.strip(), path, responses)
            except _ScpiError as err:
                self.model.push_error(err.code, err.message)
                log.debug("BOP: %s in %r", err.code, line)
                if -200 < err.code <= -100:
                    break  # a command error discards the rest of the message
        return ";".join(responses) if responses else None

    def _resolve(self, full: tuple[str, ...]) -> _Command:
        """The command a full header names; remembered, as a device's parser would have it
        compiled (a stream sends the same two headers a thousand times a second)."""
        command = self._resolved.get(full)
        if command is None:
            if any(not re.fullmatch(r"[A-Z][A-Z0-9]*", w) for w in full):
                raise _ScpiError(*SYNTAX_ERROR)
            command = next((c for c in self._commands if _matches(c.pattern, list(full))), None)
            if command is None:
                raise _ScpiError(*UNDEFINED_HEADER)
            if len(self._resolved) < 256:  # bounded: a client sending random headers
                self._resolved[full] = command
        return command

    def _execute(self, unit: str, path: list[str], responses: list[str]) -> list[str]:
        if not unit:
            raise _ScpiError(*SYNTAX_ERROR)
        header, _, parameter = unit.replace("\t", " ").partition(" ")
        header = header.upper()
        parameter = parameter.strip()
        is_query = header.endswith("?")
        if is_query:
            header = header[:-1]
        if header.startswith("*"):
            return self._common_command(header, is_query, parameter, responses, path)
        if header.startswith(":"):
            path, header = [], header[1:]
        full = path + header.split(":")
        command = self._resolve(tuple(full))
        if is_query:
            if command.query is None:
                raise _ScpiError(*UNDEFINED_HEADER)
            if parameter:
                raise _ScpiError(*PARAMETER_NOT_ALLOWED)
            responses.append(command.query())
        else:
            if command.write is None:
                raise _ScpiError(*UNDEFINED_HEADER)
            command.write(parameter)
        return full[:-1]

    def _common_command(
        self, header: str, is_query: bool, parameter: str, responses: list[str], path: list[str]
    ) -> list[str]:
        if header not in self._common:
            raise _ScpiError(*UNDEFINED_HEADER)
        write, query = self._common[header]
        action = query if is_query else write
        if action is None:
            raise _ScpiError(*UNDEFINED_HEADER)
        if parameter:
            raise _ScpiError(*PARAMETER_NOT_ALLOWED)
        result = action()
        if is_query:
            responses.append(result)  # type: ignore[arg-type]
        return path  # common commands leave the parser where it was (IEEE 488.2)
