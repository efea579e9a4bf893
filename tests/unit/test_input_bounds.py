"""Inputs that cannot hurt: a request frame is decoded within bounds (`decode_request`), and a plan
is bounded in every count, extent, time and image size before anything is allocated from it
(`parse_plan`, `check_plan`, `rigctl validate`, the six-coil realizer)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rigctl.apps.cli.main import main
from rigctl.apps.daemon.messages import (
    MAX_INT_DIGITS,
    MAX_JSON_DEPTH,
    BadJson,
    decode_request,
    read_json,
)
from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.core.errors import PlanError
from rigctl.plans.schema import (
    MAX_DURATION_S,
    MAX_MOVES,
    MAX_PROGRAM_SAMPLES,
    MAX_VERTICES,
    parse_plan,
)
from rigctl.rigs.six_coil.realize import realize_global_moves
from rigctl.rigs.six_coil.settings import SixCoilRig

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"


def fig4() -> dict:
    return json.loads((EXAMPLES / "fig4-quick.json").read_text())


@pytest.mark.parametrize("payload, says", [
    (b'{"id": "\\ud800", "cmd": "ping"}', "surrogate"),
    (b'{"cmd": "run", "args": {"\\udfff": 1}}', "surrogate"),  # a key, too
    (b'{"id": ' + b"9" * 5000 + b', "cmd": "ping"}', "5000 digits"),
    (b'{"id": ' + b"9" * (MAX_INT_DIGITS + 1) + b', "cmd": "ping"}', "digits"),
    (b"[" * 100_000 + b"]" * 100_000, "nested"),  # past the recursion limit
    (b'{"a":' * (MAX_JSON_DEPTH + 1) + b"1" + b"}" * (MAX_JSON_DEPTH + 1), "nested"),
    (b"\xff\xfe", "not JSON"),
    (b"", "not JSON"),
    (b'{"cmd": "ping"', "not JSON"),
])
def test_a_frame_that_cannot_be_a_request_is_refused_with_why(payload, says):
    with pytest.raises(BadJson, match=says):
        decode_request(payload)


def test_what_a_request_may_hold_is_read_as_json_reads_it():
    assert decode_request(b'{"id": "\\ud83d\\ude00", "x": [NaN, 1e400, -0.0]}') == {
        "id": "\U0001F600", "x": [pytest.approx(math.nan, nan_ok=True), math.inf, -0.0]}
    nested = b'{"a":' * MAX_JSON_DEPTH + b"1" + b"}" * MAX_JSON_DEPTH  # at the bound: fine
    assert isinstance(decode_request(nested), dict)
    assert decode_request(b"9" * MAX_INT_DIGITS) == int("9" * MAX_INT_DIGITS)
    long = "1" * 100  # digits in a row that are no integer: a float's, an exponent's, a string's
    assert decode_request(f'[1.{long}, {long}.5, 1e-{long}, "{long}"]'.encode()) == [
        float(f"1.{long}"), float(f"{long}.5"), 0.0, long]
    with pytest.raises(BadJson, match="an integer of 31 digits"):
        decode_request(b'{"a": "x", "b": [-' + b"1" * 31 + b"]}")


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(), inner, max_size=5),
    max_leaves=30)


@given(JSON_VALUES)
def test_read_json_reads_what_the_standard_library_reads(value):
    # integers of any size (orjson alone makes a float of one beyond 64 bits), floats, text with
    # any code point, nested: the same value and the same types, from str and from bytes
    text = json.dumps(value, ensure_ascii=False)
    expected = json.loads(text)
    for given_text in (text, text.encode()):
        got = read_json(given_text)
        assert got == expected and repr(got) == repr(expected)


PRINTABLE = st.characters(min_codepoint=0x20, max_codepoint=0x7E)
REQUEST_IDS = (st.none() | st.booleans() | st.floats(allow_nan=False) | st.text()
               | st.text(PRINTABLE, max_size=12) | st.text(PRINTABLE, min_size=120, max_size=136)
               | st.integers() | st.integers(-10**19, 10**19))


@given(REQUEST_IDS, st.sampled_from(["status", "estop", "ping", "abort"]),
       st.sampled_from([None, {}, {"immediate": True}]), st.booleans(),
       st.sampled_from([(", ", ": "), (",", ":"), (" ,\n", " :\t")]))
def test_the_quick_path_takes_only_bare_requests_and_reads_their_id_as_json_does(
        request_id, cmd, args, id_first, separators):
    from rigctl.apps.daemon.requests import QUICK_REQUEST

    fields = {"id": request_id, "cmd": cmd} if id_first else {"cmd": cmd, "id": request_id}
    if args is not None:
        fields["args"] = args
    payload = json.dumps(fields, separators=separators).encode()
    bare = (id_first and cmd in ("status", "estop") and args in (None, {})
            and type(request_id) in (int, str))
    match = QUICK_REQUEST.fullmatch(payload)
    if match is None:  # not taken: the general path answers, whatever it holds
        assert not bare or not _plain_id(request_id)
        return
    assert bare and _plain_id(request_id)
    text_id, number_id, quick_cmd = match.groups()
    assert quick_cmd.decode() == cmd
    assert (text_id.decode() if text_id is not None else int(number_id)) == request_id
    assert type(json.loads(payload)["id"]) is type(request_id)


@pytest.mark.parametrize("request_id, taken", [
    ("a" * 128, True), ("a" * 129, False), ("", True), ('a"b', False), ("a\\b", False),
    ("\u00e9", False), (10**17, True), (-(10**18 - 1), True), (10**18, False), (0, True)])
def test_the_quick_path_bounds_its_ids(request_id, taken):
    from rigctl.apps.daemon.requests import QUICK_REQUEST

    payload = json.dumps({"id": request_id, "cmd": "status", "args": {}}).encode()
    assert (QUICK_REQUEST.fullmatch(payload) is not None) == taken == _plain_id(request_id)


def _plain_id(request_id: object) -> bool:
    """What the quick path promises to take: a string of printable ASCII with nothing escaped, of
    at most 128 characters, or an integer of at most 18 digits."""
    if isinstance(request_id, str):
        return len(request_id) <= 128 and all(" " <= c <= "~" and c not in '"\\' for c in request_id)
    return len(str(abs(request_id))) <= 18


@pytest.mark.parametrize("text", ["NaN", "[Infinity, -Infinity]", '"\\ud800"', "1e400",
                                  "[9223372036854775808, -9223372036854775809]"])
def test_read_json_reads_the_python_dialect_and_the_edges_as_the_standard_library(text):
    assert repr(read_json(text)) == repr(json.loads(text))


@pytest.mark.parametrize("change, field", [
    ({"moves": [[1e300, 0.0]]}, "moves.0.0"),
    ({"moves": [[10.0, 0.0]] * (MAX_MOVES + 1)}, "moves"),
    ({"agents": [{"start": [0, 0], "goal": [1, 1], "radius": 1e300}]}, "agents.0.radius"),
    ({"tolerance_mm": math.inf}, "tolerance_mm"),
    ({"min_separation_mm": math.nan}, "min_separation_mm"),
    ({"workspace": {"boundary": {"polygon": [[i, 0] for i in range(MAX_VERTICES + 1)]}}},
     "workspace.boundary.polygon"),
    ({"workspace": {"boundary": {"rect": [0, 0, 10, 10]}, "obstacles": [{"disk": [5, 5, 1]}] * 300}},
     "workspace.obstacles"),
])
def test_an_extreme_value_in_a_plan_is_refused_naming_its_field(change, field):
    with pytest.raises(PlanError) as refused:
        parse_plan({**fig4(), **change}, "p.json")
    assert f"p.json: {field}: " in str(refused.value)


def validate(tmp_path: Path, document: dict, capsys) -> tuple[int, str]:
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(document))
    status = main(["validate", str(path)])
    return status, capsys.readouterr().err


def test_validate_refuses_a_workspace_image_that_is_not_a_png(tmp_path, capsys):
    # (one over the pixel bound: tests/integration/test_daemon_fuzz.py, with the daemon's load)
    (tmp_path / "not.png").write_bytes(b"GIF89a" + bytes(40))
    plan = {**fig4(), "workspace": {"image": "not.png", "mm_per_px": 1}}
    status, err = validate(tmp_path, plan, capsys)
    assert status == 2 and "is not a PNG" in err


def test_validate_refuses_a_plan_without_moves(tmp_path, capsys):
    plan = {**fig4(), "moves": []}
    plan.pop("expected")
    status, err = validate(tmp_path, plan, capsys)
    assert status == 2 and "moves: empty" in err


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, '{"a": ' + "9" * 5000 + "}"])
def test_validate_refuses_json_python_cannot_hold(tmp_path, capsys, text):
    (tmp_path / "plan.json").write_text(text)
    assert main(["validate", str(tmp_path / "plan.json")]) == 2
    assert capsys.readouterr().err.startswith("error: ")


def test_a_six_coil_program_over_the_sample_bound_is_refused_before_it_is_allocated():
    rig = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils())
    per_turn = 2 * math.pi * rig.magnets.radius_mm
    turns_per_move = 100
    # rolling alone: turns / (turns per s) * rate samples
    seconds = MAX_PROGRAM_SAMPLES / rig.stream.rate_hz
    moves = int(seconds * rig.field.rolling_turns_per_s / turns_per_move) + 2
    with pytest.raises(PlanError, match="samples of field program"):
        realize_global_moves(np.tile([[turns_per_move * per_turn, 0.0]], (moves, 1)), rig)


def test_a_six_coil_program_that_would_last_over_an_hour_is_refused():
    rig = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils())
    per_turn = 2 * math.pi * rig.magnets.radius_mm
    # each move: one turn (0.5 s at 2 turns/s) and the hold after it
    seconds_per_move = 1 / rig.field.rolling_turns_per_s + rig.field.hold_s
    moves = int(MAX_DURATION_S / seconds_per_move) + 10
    with pytest.raises(PlanError, match=r"lasts \d+ s; at most 3600 s"):
        realize_global_moves(np.tile([[per_turn, 0.0], [-per_turn, 0.0]], (moves // 2 + 1, 1)), rig)
    assert realize_global_moves([[per_turn, 0.0]] * 10, rig).duration_s < MAX_DURATION_S


def test_a_pair_program_over_the_sample_bound_is_refused_before_it_is_built():
    from rigctl.core.config import StreamSettings
    from rigctl.rigs.six_coil.pair import PairRunSettings, prepare_pair

    document = json.loads((EXAMPLES / "pair-formation-change.json").read_text())
    document.pop("expected", None)
    segment = document["segments"][0]
    count = 3000  # of 1 s at 1 kHz: 3e6 samples, within the plan's own bounds (segments, 1 h)
    document["segments"] = [{**segment, "dt_s": 1.0}] * count
    plan = parse_plan(document, "pair.json")
    rig = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils(),
                    stream=StreamSettings(rate_hz=1000.0))
    assert count * 1000.0 > MAX_PROGRAM_SAMPLES
    with pytest.raises(PlanError, match="samples of program at 1000 Hz"):
        prepare_pair(plan, rig, PairRunSettings())


def test_validate_does_not_read_a_plan_file_over_the_size_bound(tmp_path, capsys):
    from rigctl.plans.schema import MAX_PLAN_BYTES

    path = tmp_path / "plan.json"
    with open(path, "wb") as file:
        file.truncate(MAX_PLAN_BYTES + 1)  # sparse: nothing written
    assert main(["validate", str(path)]) == 2
    assert f"{MAX_PLAN_BYTES + 1} bytes; a plan has at most" in capsys.readouterr().err


def test_the_published_schema_states_the_bounds():
    from rigctl.plans.schema import MAX_AGENTS, MAX_VERTICES, plan_json_schema

    defs = plan_json_schema()["$defs"]
    moves = defs["GlobalMovesPlan"]["properties"]["moves"]
    assert moves["maxItems"] == MAX_MOVES and str(MAX_MOVES) in moves["description"]
    assert defs["GlobalMovesPlan"]["properties"]["agents"]["maxItems"] == MAX_AGENTS
    assert defs["PolygonShape"]["properties"]["polygon"]["maxItems"] == MAX_VERTICES
    assert defs["ImageWorkspaceSpec"]["properties"]["mm_per_px"]["minimum"] == 1e-3
