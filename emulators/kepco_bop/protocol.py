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
- IEEE 488.2 common commands, all that BOP App. A lists (Table A-1): *CLS, *ESE / *ESE?, *ESR?,
  *IDN?, *OPC / *OPC?, *OPT?, *RCL, *RST, *SAV, *SRE / *SRE?, *STB?, *TRG, *TST?, *WAI, with the
  standard's meaning: *ESE masks which *ESR? bits set the event summary (bit 5) of *STB?, *SRE
  which status byte bits set the master summary (bit 6; *SRE ignores bit 6); *ESE / *SRE take
  0-255 (-222 beyond); *TST? and DIAG:TST? answer 0 for pass (BOP par. A.17, Table A-4: a code
  otherwise; the emulator always passes and, unlike the real DIAG:TST?, does not swing the
  output); *OPC sets *ESR? bit 0 at once and *WAI returns at once because every command has
  finished before the next is read; *OPT? answers `0` (IEEE 488.2's "no options"; guess);
  *IDN? fields are a guess. *ESR? bit 7 (power on) is not set: the emulated supply starts as if
  *CLS had been sent.
- SCPI tree beyond the driver's (BOP App. B; the model holds the state, see its docstring):
  [SOURce:]CURRent|VOLTage[:LEVel]:PROTect[:BOTH] / :POSitive / :NEGative / :LIMit[:BOTH|:POSitive|
  :NEGative] / :MODE (the BOP spells it PROTect, short form PROT; `VOLT:PROT?` answers
  `positive,negative`, the negative as a negative number; only FIXed mode, no analog limits);
  CURRent|VOLTage:MODE FIXed|LIST, CURRent|VOLTage[:LEVel]:TRIGgered; CURR? / VOLT? MAX|MIN;
  LIST:CLEar, LIST:CURRent / LIST:VOLTage (append, <= 5900 points) and their :POINts?, LIST:DWELl
  and :POINts?, LIST:COUNt (0-255, 0 = forever) and :SKIP, LIST:DIRection UP|DOWN, LIST:QUERy (the
  first location LIST:CURR? / VOLT? / DWEL? answer from, 16 values at most: BIT 4886 par. B.42;
  the 16 is a guess), LIST:GENeration (DSEQuence only); INITiate[:IMMediate], INITiate:CONTinuous,
  ABORt, TRIGger[:IMMediate]; STATus:OPERation[:EVENt]? / :CONDition? / :ENABle, STATus:QUEStionable
  :ENABle, STATus:PRESet (BOP par. B.113-B.118); SYSTem:VERSion? (`1997.0`, the SCPI year Kepco's
  manuals give; guess for this firmware), SYSTem:REMote ON|OFF (the emulator is always reachable;
  it only remembers the setting), SYSTem:BEEP, SYSTem:ERRor:CODE[:NEXT]? / :CODE:ALL? (codes only;
  ALL empties the queue: MST 488 par. B.47-B.48, guess for the BOP); DIAGnostic:TST?.
- Also: CURRent|VOLTage[:LEVel]:LIMit[:BOTH|:POSitive|:NEGative] (software limits, 0 to the
  rating: settings beyond them get -222 and MAX / MIN mean them, BOP par. B.2, B.21-B.24);
  OUTPut:MODE ACTive|RESistive|BATTery (B.15-B.16; remembered, the emulated off state is always
  the active one, right for a coil). MEASure[:SCALar]:CURRent|VOLTage[:DC]? in all its long and
  short forms; with a parameter it is -108 (Kepco's MST 488 par. B.10 accepts SCPI's range and
  resolution there and sets questionable bit 13; the BOP manual is silent, so we keep the error).
- Not emulated (answered -113 like any unknown header): CAL, MEM, DISPlay, LIST:SEQuence and
  LIST:SAMPle, SYST:PASS / KLOC / SEC / SET.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.emulators.kepco_bop.model import (
    DATA_OUT_OF_RANGE,
    LIST_MAX_POINTS,
    PROTECTION_MARGIN,
    SETTINGS_CONFLICT,
    BopCoilModel,
)

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
    query: Callable[[str], str] | None  # receives the parameter text (most take none)


def _bare(answer: Callable[[], str]) -> Callable[[str], str]:
    """A query that takes no parameter (-108 if one is sent)."""
    def query(text: str) -> str:
        if text:
            raise _ScpiError(*PARAMETER_NOT_ALLOWED)
        return answer()
    return query


def _action(act: Callable[[], object]) -> Callable[[str], None]:
    """A command that takes no parameter (-108 if one is sent)."""
    def write(text: str) -> None:
        if text:
            raise _ScpiError(*PARAMETER_NOT_ALLOWED)
        act()
    return write


def _number(text: str, *, maximum: float, minimum: float | None = None) -> float:
    """An NRf parameter, or MAX / MIN (the most positive / negative allowed value; MIN is
    -maximum unless given)."""
    word = text.strip().upper()
    if not word:
        raise _ScpiError(*MISSING_PARAMETER)
    if word in ("MAX", "MAXIMUM"):
        return maximum
    if word in ("MIN", "MINIMUM"):
        return -maximum if minimum is None else minimum
    if not _NRF.fullmatch(word):
        raise _ScpiError(*NUMERIC_DATA_ERROR)
    value = float(word)
    if not math.isfinite(value) or abs(value) > MAX_NUMERIC_MAGNITUDE:
        raise _ScpiError(*NUMERIC_DATA_ERROR)
    return value


def _numbers(text: str, *, maximum: float) -> list[float]:
    """A comma-separated list of NRf parameters (LIST:CURR 1,2.5,-3)."""
    if not text.strip():
        raise _ScpiError(*MISSING_PARAMETER)
    return [_number(part, maximum=maximum) for part in text.split(",")]


def _integer(text: str, low: int, high: int) -> int:
    """An NRf parameter rounded to an integer (IEEE 488.2 does so), -222 outside [low, high]."""
    value = round(_number(text, maximum=high))
    if not low <= value <= high:
        raise _ScpiError(*DATA_OUT_OF_RANGE)
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


def _choice(text: str, choices: dict[str, str]) -> str:
    """A character parameter in short or long form: `choices` maps both to the canonical word."""
    word = text.strip().upper()
    if not word:
        raise _ScpiError(*MISSING_PARAMETER)
    if word not in choices:
        raise _ScpiError(*SYNTAX_ERROR)
    return choices[word]


def _scientific(value: float) -> str:
    return f"{value + 0.0:.6E}"


LIST_QUERY_VALUES = 16  # values one LIST:CURR? / VOLT? / DWEL? answers (BIT 4886 par. B.42; guess)
SCPI_VERSION = "1997.0"  # SYST:VERS? (the SCPI year Kepco's manuals give; guess for this firmware)


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
        self.remote = True  # SYST:REM (the emulator is reached only remotely; it remembers)
        self._list_query_start = 0
        self._responses: list[str] = []  # of the message being executed (*STB?'s MAV bit)
        m = self.model
        # IEEE 488.2 common commands (BOP App. A): header -> (command, query)
        self._common: dict[str, tuple[Callable[[str], None] | None, Callable[[str], str] | None]] = {
            "*CLS": (_action(m.clear_status), None),
            "*ESE": (self._set_event_status_enable, _bare(lambda: str(m.event_status_enable))),
            "*ESR": (None, _bare(lambda: str(m.read_event_status()))),
            "*IDN": (None, _bare(lambda: self._idn)),
            "*OPC": (_action(m.operation_complete), _bare(lambda: "1")),
            "*OPT": (None, _bare(lambda: "0")),
            "*RCL": (lambda text: m.recall_setup(_integer(text, 0, 99)), None),
            "*RST": (_action(m.reset), None),
            "*SAV": (lambda text: m.save_setup(_integer(text, 0, 99)), None),
            "*SRE": (self._set_service_request_enable,
                     _bare(lambda: str(m.service_request_enable))),
            "*STB": (None, _bare(lambda: str(m.status_byte(bool(self._responses))))),
            "*TRG": (_action(m.trigger), None),
            "*TST": (None, _bare(lambda: "0")),
            "*WAI": (_action(lambda: None), None),
        }
        self._resolved: dict[tuple[str, ...], _Command] = {}
        self._commands = [
            _Command(_parse_pattern("[SOURce] FUNCtion MODE"), self._set_mode,
                     _bare(lambda: "1" if m.mode == "CURR" else "0")),
            *self._channel_commands("CURR", "CURRent", lambda: m.current_limit_A),
            *self._channel_commands("VOLT", "VOLTage", lambda: m.compliance_V),
            _Command(_parse_pattern("OUTPut [STATe]"), self._set_output,
                     _bare(lambda: "1" if m.output_on else "0")),
            _Command(_parse_pattern("OUTPut MODE"), self._set_output_mode,
                     _bare(lambda: m.output_mode)),
            _Command(_parse_pattern("MEASure [SCALar] CURRent [DC]"), None,
                     _bare(lambda: _scientific(m.current_A))),
            _Command(_parse_pattern("MEASure [SCALar] VOLTage [DC]"), None,
                     _bare(lambda: _scientific(m.voltage_V))),
            # the list (BOP App. B LIST commands; the model's docstring says how it runs)
            _Command(_parse_pattern("[SOURce] LIST CLEar"), _action(self._clear_list), None),
            _Command(_parse_pattern("[SOURce] LIST CURRent"),
                     lambda text: m.add_list_points("CURR", _numbers(text, maximum=m.current_limit_A)),
                     _bare(lambda: self._list_values(m.list_points if m.list_channel == "CURR" else []))),
            _Command(_parse_pattern("[SOURce] LIST CURRent POINts"), None,
                     _bare(lambda: str(len(m.list_points) if m.list_channel == "CURR" else 0))),
            _Command(_parse_pattern("[SOURce] LIST VOLTage"),
                     lambda text: m.add_list_points("VOLT", _numbers(text, maximum=m.compliance_V)),
                     _bare(lambda: self._list_values(m.list_points if m.list_channel == "VOLT" else []))),
            _Command(_parse_pattern("[SOURce] LIST VOLTage POINts"), None,
                     _bare(lambda: str(len(m.list_points) if m.list_channel == "VOLT" else 0))),
            _Command(_parse_pattern("[SOURce] LIST DWELl"),
                     lambda text: m.add_list_dwells(_numbers(text, maximum=MAX_NUMERIC_MAGNITUDE)),
                     _bare(lambda: self._list_values(m.list_dwell_s))),
            _Command(_parse_pattern("[SOURce] LIST DWELl POINts"), None,
                     _bare(lambda: str(len(m.list_dwell_s)))),
            _Command(_parse_pattern("[SOURce] LIST COUNt"),
                     lambda text: self._set_list("list_count", _integer(text, 0, 255)),
                     _bare(lambda: str(m.list_count))),
            _Command(_parse_pattern("[SOURce] LIST COUNt SKIP"),
                     lambda text: self._set_list("list_skip", _integer(text, 0, 255)),
                     _bare(lambda: str(m.list_skip))),
            _Command(_parse_pattern("[SOURce] LIST DIRection"),
                     lambda text: self._set_list("list_direction",
                                                 _choice(text, {"UP": "UP", "DOWN": "DOWN"})),
                     _bare(lambda: m.list_direction)),
            _Command(_parse_pattern("[SOURce] LIST QUERy"), self._set_list_query,
                     _bare(lambda: str(self._list_query_start))),
            _Command(_parse_pattern("[SOURce] LIST GENeration"), self._set_list_generation,
                     _bare(lambda: "DSEQ")),
            # trigger (BOP par. 3.6.3.1, 3.6.3.3, B.3)
            _Command(_parse_pattern("INITiate [IMMediate]"), _action(m.arm_trigger), None),
            _Command(_parse_pattern("INITiate CONTinuous"),
                     lambda text: m.arm_trigger(_boolean(text)),
                     _bare(lambda: "1" if m.trigger_continuous else "0")),
            _Command(_parse_pattern("ABORt"), _action(m.abort_trigger), None),
            _Command(_parse_pattern("TRIGger [IMMediate]"), _action(m.trigger), None),
            # status (BOP par. 3.6.7, B.113-B.118)
            _Command(_parse_pattern("STATus OPERation [EVENt]"), None,
                     _bare(lambda: str(m.read_operation_event()))),
            _Command(_parse_pattern("STATus OPERation CONDition"), None,
                     _bare(lambda: str(m.operation_condition()))),
            _Command(_parse_pattern("STATus OPERation ENABle"),
                     lambda text: setattr(m, "operation_enable", _integer(text, 0, 65535)),
                     _bare(lambda: str(m.operation_enable))),
            _Command(_parse_pattern("STATus QUEStionable CONDition"), None,
                     _bare(lambda: str(m.questionable_condition()))),
            _Command(_parse_pattern("STATus QUEStionable [EVENt]"), None,
                     _bare(lambda: str(m.read_questionable_event()))),
            _Command(_parse_pattern("STATus QUEStionable ENABle"),
                     lambda text: setattr(m, "questionable_enable", _integer(text, 0, 65535)),
                     _bare(lambda: str(m.questionable_enable))),
            _Command(_parse_pattern("STATus PRESet"), _action(m.preset_status), None),
            # system and diagnostics
            _Command(_parse_pattern("SYSTem ERRor [NEXT]"), None, _bare(self._next_error)),
            _Command(_parse_pattern("SYSTem ERRor CODE [NEXT]"), None,
                     _bare(lambda: str(m.pop_error()[0]))),
            _Command(_parse_pattern("SYSTem ERRor CODE ALL"), None, _bare(self._all_error_codes)),
            _Command(_parse_pattern("SYSTem VERSion"), None, _bare(lambda: SCPI_VERSION)),
            _Command(_parse_pattern("SYSTem REMote"),
                     lambda text: setattr(self, "remote", _boolean(text)),
                     _bare(lambda: "1" if self.remote else "0")),
            _Command(_parse_pattern("SYSTem BEEP"), _action(lambda: None), None),
            _Command(_parse_pattern("DIAGnostic TST"), None, _bare(lambda: "0")),
        ]

    def _channel_commands(self, short: str, long: str, rating: Callable[[], float]) -> list[_Command]:
        """The CURRent or VOLTage branch: level, triggered level, mode, protection limits."""
        m = self.model
        channel = short  # "CURR" | "VOLT"
        level = "[SOURce] " + long + " [LEVel]"
        setpoint = ((lambda: m.current_setpoint_A) if channel == "CURR"
                    else (lambda: m.voltage_setpoint_V))
        write_level = self._set_current if channel == "CURR" else self._set_voltage
        trigger_attr = "current_trigger_A" if channel == "CURR" else "voltage_trigger_V"
        limits = ((lambda: m.current_protection_A) if channel == "CURR"
                  else (lambda: m.voltage_protection_V))
        maxima = ((lambda: m.current_protection_max_A) if channel == "CURR"
                  else (lambda: m.voltage_protection_max_V))

        soft = ((lambda: m.current_soft_limit_A) if channel == "CURR"
                else (lambda: m.voltage_soft_limit_V))

        def level_query(text: str) -> str:  # CURR? [MAX|MIN] (BOP par. B.20)
            if not text:
                return _scientific(setpoint())
            if text.strip().upper() not in ("MAX", "MAXIMUM", "MIN", "MINIMUM"):
                raise _ScpiError(*SYNTAX_ERROR)
            return _scientific(_number(text, maximum=soft()[0], minimum=-soft()[1]))

        def soft_limit(side: str) -> Callable[[str], None]:
            return lambda text: m.set_soft_limit(
                channel, _number(text, maximum=rating()), side)  # type: ignore[arg-type]

        def trigger_write(text: str) -> None:
            value = _number(text, maximum=rating())
            if abs(value) > rating():
                raise _ScpiError(*DATA_OUT_OF_RANGE)
            setattr(m, trigger_attr, value)

        def trigger_query() -> str:
            value = getattr(m, trigger_attr)
            return _scientific(setpoint() if value is None else value)

        def mode_write(text: str) -> None:
            if _choice(text, {"FIX": "FIX", "FIXED": "FIX", "LIST": "LIST"}) == "LIST":
                if m.mode != channel:
                    raise _ScpiError(*SETTINGS_CONFLICT)
                m.start_list()
            elif m.mode == channel:
                m.stop_list()

        def protect(side: str, maximum: bool = False) -> Callable[[str], None]:
            return lambda text: m.set_protection(
                channel, _number(text, maximum=PROTECTION_MARGIN * rating()), side,  # type: ignore[arg-type]
                maximum=maximum)

        def pair(values: Callable[[], list[float]]) -> Callable[[str], str]:
            return _bare(lambda: f"{_scientific(values()[0])},{_scientific(-values()[1])}")

        def one(values: Callable[[], list[float]], k: int) -> Callable[[str], str]:
            return _bare(lambda: _scientific(values()[k] if k == 0 else -values()[k]))

        prot = level + " PROTect"
        return [
            _Command(_parse_pattern(level + " [IMMediate] [AMPlitude]"), write_level, level_query),
            _Command(_parse_pattern(level + " TRIGgered [AMPlitude]"), trigger_write,
                     _bare(trigger_query)),
            _Command(_parse_pattern("[SOURce] " + long + " MODE"), mode_write,
                     _bare(lambda: "LIST" if m.list_running and m.mode == channel else "FIX")),
            _Command(_parse_pattern(prot + " [BOTH]"), protect("BOTH"), pair(limits)),
            _Command(_parse_pattern(prot + " POSitive"), protect("POS"), one(limits, 0)),
            _Command(_parse_pattern(prot + " NEGative"), protect("NEG"), one(limits, 1)),
            _Command(_parse_pattern(prot + " LIMit [BOTH]"), protect("BOTH", True), pair(maxima)),
            _Command(_parse_pattern(prot + " LIMit POSitive"), protect("POS", True), one(maxima, 0)),
            _Command(_parse_pattern(prot + " LIMit NEGative"), protect("NEG", True), one(maxima, 1)),
            _Command(_parse_pattern(level + " LIMit [BOTH]"), soft_limit("BOTH"), pair(soft)),
            _Command(_parse_pattern(level + " LIMit POSitive"), soft_limit("POS"), one(soft, 0)),
            _Command(_parse_pattern(level + " LIMit NEGative"), soft_limit("NEG"), one(soft, 1)),
            _Command(_parse_pattern(prot + " MODE"),  # only the fixed (digital) limits exist here
                     lambda text: None if _choice(text, {"FIX": "FIX", "FIXED": "FIX", "EXT": "EXT",
                                                         "EXTERNAL": "EXT", "LESS": "LESS",
                                                         "LESSER": "LESS"}) == "FIX"
                     else self._conflict(), _bare(lambda: "FIX")),
        ]

    # -- command actions ------------------------------------------------------------------------

    @staticmethod
    def _conflict() -> None:
        raise _ScpiError(*SETTINGS_CONFLICT)

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
        high, low = self.model.current_soft_limit_A
        self.model.set_current(_number(text, maximum=high, minimum=-low))

    def _set_voltage(self, text: str) -> None:
        high, low = self.model.voltage_soft_limit_V
        self.model.set_voltage(_number(text, maximum=high, minimum=-low))

    def _set_output(self, text: str) -> None:
        self.model.set_output(_boolean(text))

    def _set_output_mode(self, text: str) -> None:
        self.model.output_mode = _choice(text, {"ACT": "ACTIVE", "ACTIVE": "ACTIVE",
                                                "RES": "RESISTIVE", "RESISTIVE": "RESISTIVE",
                                                "BATT": "BATTERY", "BATTERY": "BATTERY"})

    def _set_event_status_enable(self, text: str) -> None:
        self.model.event_status_enable = _integer(text, 0, 255)

    def _set_service_request_enable(self, text: str) -> None:
        # IEEE 488.2: bit 6 (the master summary itself) cannot be enabled; it reads back 0
        self.model.service_request_enable = _integer(text, 0, 255) & ~64

    def _next_error(self) -> str:
        code, message = self.model.pop_error()
        return f'{code},"{message}"'

    def _all_error_codes(self) -> str:
        codes = []
        while self.model.error_count:
            codes.append(str(self.model.pop_error()[0]))
        return ",".join(codes) if codes else "0"

    def _clear_list(self) -> None:
        if self.model.list_running:
            raise _ScpiError(*SETTINGS_CONFLICT)
        self.model.clear_list()
        self._list_query_start = 0

    def _set_list(self, attribute: str, value: object) -> None:
        if self.model.list_running:
            raise _ScpiError(*SETTINGS_CONFLICT)
        setattr(self.model, attribute, value)

    @staticmethod
    def _set_list_generation(text: str) -> None:
        """LIST:GEN: only the default sequence (DSEQ) is emulated; SEQ (LIST:SEQ) answers -102."""
        _choice(text, {"DSEQ": "DSEQ", "DSEQUENCE": "DSEQ"})

    def _set_list_query(self, text: str) -> None:
        self._list_query_start = _integer(text, 0, LIST_MAX_POINTS - 1)

    def _list_values(self, values: list[float]) -> str:
        start = self._list_query_start
        return ",".join(_scientific(v) for v in values[start:start + LIST_QUERY_VALUES])

    # -- parsing --------------------------------------------------------------------------------

    def handle(self, line: str) -> str | None:
        """Execute one program message; the joined query responses, or None if there were none."""
        self._before_command()
        responses: list[str] = []
        self._responses = responses
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
            responses.append(command.query(parameter))
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
        if is_query:
            if query is None:
                raise _ScpiError(*UNDEFINED_HEADER)
            responses.append(query(parameter))
        else:
            if write is None:
                raise _ScpiError(*UNDEFINED_HEADER)
            write(parameter)
        return path  # common commands leave the parser where it was (IEEE 488.2)
