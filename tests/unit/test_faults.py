"""The fault campaign's judgement of a cell (`rigctl.apps.faults`): the outcome read from a run record,
whether a record is complete / readable / lost, the cells a campaign plans, and the matrix that
marks failed cells. Records are written with the real `RunRecord`; runs are not started here (the
campaign itself runs in tests/e2e/test_faults_cli.py)."""

from __future__ import annotations

import pytest

from rigctl.apps.faults import (
    PHASES,
    STREAM_PROCESS,
    Cell,
    campaign_faults,
    check_record,
    every_cell_ok,
    fault_profile,
    figures,
    matrix,
    outcome_of,
    parse_cell,
    planned_cells,
    profiled_kinds,
    rig_profile,
    stop_latency,
)
from rigctl.core.record import RunRecord
from rigctl.rigs.faults import Fault


def state(name: str, **info) -> dict:
    return {"event": "state", "state": name, **info}


def test_a_run_that_suspended_and_resumed_and_ended_done_is_named_so():
    events = [state("running"), state("suspended", reason="tracking lost"), state("running"),
              state("done")]
    assert outcome_of(events, {"state": "done", "faults": []})[0] == "suspended and resumed"
    assert outcome_of([state("running"), state("done")], {"state": "done", "faults": []}) == \
        ("completed", None, None)
    assert outcome_of([state("running"), state("paused"), state("running"), state("done")],
                      {"state": "done", "faults": []})[0] == "paused and resumed"


def test_a_device_fault_names_the_device_even_when_an_abort_ended_the_run():
    fault = {"device": "x+", "reason": "x+: no reply within 0.5 s (watchdog)", "kind": "DeviceTimeout"}
    summary = {"state": "aborted", "faults": [fault, {"device": None, "reason": "aborted by the "
                                                      "operator", "kind": "Abort"}]}
    assert outcome_of([state("running"), state("faulted"), state("aborted")], summary) == \
        ("faulted", "x+", fault["reason"])
    # an abort alone is an abort
    assert outcome_of([state("running"), state("aborted")], {"state": "aborted", "faults": [
        {"device": None, "reason": "aborted by the operator", "kind": "Abort"}]})[0] == "aborted"


def test_estop_refusal_and_a_record_without_summary():
    assert outcome_of([state("estopped")], {"state": "estopped", "faults": [
        {"device": None, "reason": "emergency stop", "kind": "EStop"}]})[0] == "e-stopped"
    assert outcome_of([], {"state": None, "faults": [], "refused": "x+: link lost"}) == \
        ("refused", None, "x+: link lost")
    died = {"event": "fault", "device": None, "reason": "the stream process died",
            "kind": "StreamProcessDied"}
    assert outcome_of([state("running"), died], None) == ("faulted", None, died["reason"])
    assert outcome_of([state("running")], None)[0] is None  # nothing says how it ended


def test_a_record_is_complete_readable_incomplete_or_lost(tmp_path):
    assert check_record(None) == ("lost", None)
    assert check_record(tmp_path / "nothing")[0] == "lost"

    whole = RunRecord(tmp_path, "whole")
    whole.write_file("plan.json", "{}")
    whole.event("state", state="running")
    whole.event("state", state="done")
    whole.finish({"state": "done"})
    assert check_record(whole.path) == ("complete", whole.path.name)

    # the stream process killed: no summary, the daemon appended the fault
    cut = RunRecord(tmp_path, "cut")
    cut.write_file("plan.json", "{}")
    cut.event("state", state="running")
    cut.event("fault", device=None, reason="the stream process died", kind="StreamProcessDied")
    cut.close()
    assert check_record(cut.path)[0] == "readable"

    # nothing says how it ended
    open_ended = RunRecord(tmp_path, "open")
    open_ended.event("state", state="running")
    open_ended.close()
    assert check_record(open_ended.path)[0] == "incomplete"

    # it says it energised, but there is no stream to read
    no_stream = RunRecord(tmp_path, "nostream")
    no_stream.event("energised", devices=["x+"])
    no_stream.finish({"state": "done"})
    assert check_record(no_stream.path)[0] == "incomplete"


KINDS = {"x+": ["drop_link", "stall", "corrupt", "overtemp"],
         "x-": ["drop_link", "stall", "corrupt", "overtemp"],
         "camera": ["drop_frames", "freeze", "black_out", "occlude", "drop_link"]}


def test_one_device_stands_for_each_class_and_the_daemons_own_faults_join():
    labels = [f.label for f in campaign_faults(KINDS)]
    assert labels == ["x+:drop_link", "x+:stall", "x+:corrupt", "x+:overtemp",
                      "camera:drop_frames", "camera:freeze", "camera:black_out", "camera:occlude",
                      "camera:drop_link", f"{STREAM_PROCESS}:sigkill", f"{STREAM_PROCESS}:sigstop"]
    assert len(campaign_faults(KINDS, all_devices=True)) == 4 + 4 + 5 + 2
    faults = {f.label: f for f in campaign_faults(KINDS)}
    assert faults["camera:occlude"].args == (("robot", 0),)
    assert faults[f"{STREAM_PROCESS}:sigstop"].clear == "SIGCONT"
    assert faults[f"{STREAM_PROCESS}:sigkill"].clear is None


def test_cell_names_are_checked():
    assert parse_cell("daemon/x+:stall/moving") == ("daemon", "x+:stall", "moving")
    for bad in ("daemon/x+:stall", "local/x+:stall/moving", "daemon/x+/moving",
                "daemon/x+:stall/flying"):
        with pytest.raises(ValueError, match="PATH/DEVICE:KIND/PHASE"):
            parse_cell(bad)
    assert PHASES == ("before", "moving", "paused", "suspended", "ramping")


def test_the_matrix_marks_a_cell_not_safe_and_the_figures_take_the_worst_stopped_cell():
    cells = [
        Cell("six-coil", "daemon", "x+:drop_link", "moving", outcome="faulted", device="x+",
             fault_to_safe_s=0.3, safe=True, record="complete"),
        Cell("six-coil", "daemon", "x+:stall", "ramping", outcome="faulted", device="x+",
             fault_to_safe_s=None, safe=False, record="complete", note="not safe at the end"),
        Cell("six-coil", "daemon", "camera:freeze", "moving", outcome="completed",
             fault_to_safe_s=7.0, safe=True, record="complete"),
        Cell("six-coil", "daemon", "x+:drop_link", "suspended", outcome="faulted",
             fault_to_safe_s=1.2, safe=True, record="lost"),
    ]
    assert [c.ok for c in cells] == [True, False, True, False]
    assert not every_cell_ok(cells) and every_cell_ok(cells[:1])
    text = matrix(cells)
    assert "!FAULT -" in text and "FAULT 0.30" in text and "done 7.00" in text
    assert "4 cells, 2 failed" in text
    assert "! six-coil daemon x+:stall @ ramping" in text
    rig = figures(cells)["six-coil"]
    # the run the camera fault did not stop is not a time to safe: 1.2 s (a stopped run) is
    assert rig["worst_fault_to_safe_s"] == 1.2 and rig["failed"] == 2
    assert rig["outcomes"] == {"faulted": 3, "completed": 1}


def test_the_stop_latency_is_read_from_the_record_and_its_worst_is_held_to_one_period():
    events = [{"t": 0.0, "event": "prepared", "rate_hz": 1000.0},
              {"t": 2.0, "event": "fault", "device": "x+"},
              {"t": 2.0004, "event": "stopping", "ramp_s": 0.2, "after_decision_s": 0.0004}]
    assert stop_latency(events) == (0.0004, 0.001)
    assert stop_latency(events[:1]) == (None, 0.001)  # killed before it stopped: no time
    assert stop_latency([]) == (None, None)
    cells = [Cell("six-coil", "daemon", "x+:drop_link", "moving", outcome="faulted", safe=True,
                  record="complete", decision_to_stopping_s=0.0004, stream_period_s=0.001),
             Cell("six-coil", "execute", "x+:stall", "moving", outcome="faulted", safe=True,
                  record="complete", decision_to_stopping_s=0.0031, stream_period_s=0.001),
             Cell("six-coil", "daemon", "stream:SIGKILL", "moving", outcome="faulted", safe=True,
                  record="readable")]
    rig = figures(cells)["six-coil"]
    assert rig["worst_decision_to_stopping_s"] == 0.0031 and rig["stopping_timed"] == 2
    assert rig["worst_stopping_cell"] == "execute x+:stall @ moving"
    assert rig["stream_period_s"] == 0.001
    assert "worst 3.10 ms (execute x+:stall @ moving), one stream period 1.0 ms: OVER" \
        in matrix(cells)
    assert "one stream period 1.0 ms: within" in matrix(cells[:1])


def test_each_kind_with_a_profile_gives_a_plan_for_itself_and_quick_cells_the_campaign_reads():
    """The campaign asks each installed kind for its profile: its short plan is a plan for that
    kind (the six-coil one is read from plans/examples, wherever rigctl is installed), and its quick
    cells are cells the campaign can parse. (The six-coil plan's path, taken beside the module
    that read it, was lost when the campaign moved into rigctl/apps.)"""
    from rigctl.plans.schema import parse_plan

    kinds = profiled_kinds()
    assert kinds, "no installed kind has a fault profile"
    for name in kinds:
        profile = rig_profile(name)
        plan = parse_plan(profile.plan(), f"{name}'s fault plan")
        assert plan.rig == name
        for path, label, phase in profile.quick:
            assert parse_cell(f"{path}/{label}/{phase}") == (path, label, phase)


def _bare_kind():
    from rigctl.rigs.base import RigKind

    return RigKind(name="spinner", description="a magnet on a stepper", plans={},
                   channels=lambda rig: [], devices=lambda rig: [], make_safe=lambda rig: {},
                   hold=lambda rig, target: None)


def test_a_kind_without_a_fault_profile_is_refused_in_one_line_naming_those_with_one():
    from rigctl.core.errors import ConfigError

    bare = _bare_kind()
    with pytest.raises(ConfigError) as refused:
        fault_profile(bare)
    message = str(refused.value)
    assert "\n" not in message and "'spinner' has no fault profile" in message
    assert all(name in message for name in profiled_kinds())
    with pytest.raises(ConfigError, match="'no-such-kind' is not installed"):
        rig_profile("no-such-kind")


def test_rigctl_faults_runs_the_kinds_with_a_profile_and_refuses_one_without(monkeypatch, capsys):
    """`rigctl faults --rig KIND` for an installed kind with no profile: one line, exit 2, no bench
    started; the campaign's kinds are the installed ones with a profile (asked of the registry,
    here with one more kind installed that has none)."""
    from rigctl.apps import faults
    from rigctl.apps.cli.main import main
    from rigctl.core.errors import EXIT_BAD_INPUT
    from rigctl.core.registry import kinds

    installed = {**kinds(), "spinner": _bare_kind()}
    monkeypatch.setattr(faults, "kinds", lambda: installed)
    monkeypatch.setattr(faults, "rig_kind", installed.__getitem__)
    assert {"six-coil", "coil-board", "depm"} <= set(profiled_kinds())
    assert "spinner" not in profiled_kinds()
    assert main(["faults", "--rig", "spinner", "--quick"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'spinner' has no fault profile" in err
    assert "starting its emulated bench" not in err


def test_a_cell_named_wrong_is_refused_in_one_line_before_any_bench_starts(capsys):
    from rigctl.apps.cli.main import main
    from rigctl.core.errors import EXIT_BAD_INPUT

    assert main(["faults", "--rig", "coil-board", "--cell", "daemon/board:stall/flying"]) == \
        EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'daemon/board:stall/flying'" in err and "moving" in err
    assert "starting its emulated bench" not in err


def test_the_cells_named_are_the_ones_planned():
    """`--cell` (run_campaign's `only`): exactly those, in that order, each fault the bench's."""
    freeze, stall = Fault("camera", "freeze"), Fault("board", "stall")

    class Campaign:  # the part of a RigCampaign planned_cells reads
        faults = [freeze, stall]

        def fault(self, label):
            return next(f for f in self.faults if f.label == label)

    assert planned_cells(Campaign(), quick=True, only=["daemon/camera:freeze/moving",
                                                       "execute/board:stall/moving"]) == [
        ("daemon", freeze, "moving"), ("execute", stall, "moving")]
