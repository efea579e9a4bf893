"""`rigctl report`: records written with `RunRecord` as the runs write them (channels with units
and limits, tracked positions, a re-plan, a fault, the dual-EPM field series), drawn, and the
figure's axes checked against what was recorded: which panels, their units, the limit lines at
the channels' limits, the fault and re-plan marks at their events' times, the measured path
through the tracked positions, the field requests from the plan's segments."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rigctl.apps.report import build_figure, render_report
from rigctl.core.channels import Channel
from rigctl.core.record import RunRecord, read_events

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

GLOBAL_PLAN = {
    "schema": "rigctl.plan/1", "name": "synthetic two magnets", "kind": "global-moves",
    "rig": "six-coil",
    "workspace": {"boundary": {"rect": [0, 0, 100, 80]}, "obstacles": [{"rect": [40, 0, 10, 30]}]},
    "agents": [{"start": [10.0, 60.0], "goal": [90.0, 60.0], "radius": 3.0},
               {"start": [10.0, 40.0], "goal": [90.0, 40.0], "radius": 3.0}],
    "moves": [[40.0, 0.0], [40.0, 0.0]],
    "expected": [[[50.0, 60.0], [50.0, 40.0]], [[90.0, 60.0], [90.0, 40.0]]],
    "tolerance_mm": 1.0,
}
SUPPLIES = [Channel("x+", "A", -20.0, 20.0, "supplies"), Channel("x-", "A", -20.0, 20.0, "supplies"),
            Channel("y+", "A", -12.5, 12.5, "supplies")]


def by_gid(fig, gid: str):
    found = [ax for ax in fig.axes if ax.get_gid() == gid]
    assert len(found) == 1, [ax.get_gid() for ax in fig.axes]
    return found[0]


def lines(ax, gid: str):
    return [line for line in ax.get_lines() if line.get_gid() == gid]


def figure_text(fig) -> str:
    texts = [t.get_text() for t in fig.texts]
    for sub in fig.subfigs:
        texts += [t.get_text() for t in sub.texts]
    return "\n".join(texts)


@pytest.fixture
def global_moves_record(tmp_path):
    """A six-coil run: 30 stream cycles, tracked positions, a re-plan, then a fault."""
    record = RunRecord(tmp_path, GLOBAL_PLAN["name"])
    record.write_file("plan.json", json.dumps(GLOBAL_PLAN))
    record.event("prepared", rate_hz=100.0)
    record.open_stream(SUPPLIES, rate_hz=100.0)
    tracked = []
    for k in range(30):
        commanded = [5.0 * math.sin(k / 5), 5.0 * math.sin(k / 5), -3.0]
        measured = [c * 0.98 for c in commanded]
        record.stream_row(k, 0 if k < 15 else 1, commanded, measured, period_error_s=1e-4 * k)
        if k % 5 == 0:
            positions = [[10.0 + 2 * k, 60.0 + 0.1 * k], [10.0 + 2 * k, 40.0 - 0.1 * k]]
            tracked.append(positions)
            record.event("tracked", positions_mm=positions, lost=[False, False], frame=k)
        if k == 12:
            record.event("replan", sample=k, reason="off the plan")
    record.event("fault", device="y+", reason="y+: no reply within 0.25 s", kind="DeviceTimeout")
    record.finish({"reached": False, "state": "faulted", "safe": True, "unsafe_devices": [],
                   "rig": "six-coil", "plan_kind": "global-moves",
                   "agents": [{"final": [68.0, 63.0], "goal": [90.0, 60.0], "error_mm": 22.2},
                              {"final": [68.0, 37.0], "goal": [90.0, 40.0], "error_mm": 22.2}],
                   "tolerance_mm": 1.0, "replans": 1, "tracking": None,
                   "faults": [{"device": "y+", "reason": "y+: no reply within 0.25 s"}],
                   "stream": None, "metrics": {}})
    return record.path, np.array(tracked)


def test_a_camera_rig_record_draws_paths_currents_and_timing(global_moves_record):
    run_dir, tracked = global_moves_record
    events = read_events(run_dir)
    fault_t = next(e["t"] for e in events if e["event"] == "fault")
    replan_t = next(e["t"] for e in events if e["event"] == "replan")
    fig = build_figure(run_dir)

    assert sorted(ax.get_gid() for ax in fig.axes) == ["actuators:supplies", "paths", "period"]
    paths = by_gid(fig, "paths")
    assert (paths.get_xlabel(), paths.get_ylabel()) == ("x (mm)", "y (mm)")
    for i, agent in enumerate(GLOBAL_PLAN["agents"]):
        (planned,) = lines(paths, f"planned {i}")
        expected = [agent["start"]] + [step[i] for step in GLOBAL_PLAN["expected"]]
        np.testing.assert_allclose(planned.get_xydata(), expected)
        (measured,) = lines(paths, f"measured {i}")
        xy = measured.get_xydata()
        np.testing.assert_allclose(xy[:-1], tracked[:, i])  # the tracked events, in order
        np.testing.assert_allclose(xy[-1], [68.0, 63.0 if i == 0 else 37.0])  # then the final

    currents = by_gid(fig, "actuators:supplies")
    assert currents.get_ylabel() == "current (A)"
    limit_values = sorted({line.get_ydata()[0] for line in lines(currents, "limit")})
    assert limit_values == [-20.0, -12.5, 12.5, 20.0]
    # x+ and x- are commanded alike: one dashed trace for both, a solid one each
    commanded = [line.get_gid() for line in currents.get_lines()
                 if (line.get_gid() or "").startswith("commanded")]
    assert commanded == ["commanded x+ x-", "commanded y+"]
    assert len(lines(currents, "measured x+")) == len(lines(currents, "measured x-")) == 1

    for ax in (currents, by_gid(fig, "period")):  # every time axis
        (fault,) = lines(ax, "fault")
        assert fault.get_xdata()[0] == pytest.approx(fault_t)
        assert fault.get_color() == "red"
        (replan,) = lines(ax, "replan")
        assert replan.get_xdata()[0] == pytest.approx(replan_t)
    # one time axis for both (shared), labelled below the lower one
    assert by_gid(fig, "period").get_xlabel() == "time since the run started (s)"
    assert by_gid(fig, "period").get_ylabel() == "period error (ms)"
    text = figure_text(fig)
    assert "stopped: y+: no reply within 0.25 s" in text and "state faulted" in text


def test_render_report_writes_the_png(global_moves_record, tmp_path):
    run_dir, _ = global_moves_record
    out = render_report(run_dir, tmp_path / "report.png")
    png = out.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert render_report(run_dir) == run_dir / "report.png"


DEPM_PLAN = {
    "schema": "rigctl.plan/1", "name": "synthetic field sequence", "kind": "field-sequence",
    "rig": "depm",
    "segments": [
        {"name": "Bx", "U": [10, 0, 0, 0, 0, 0, 0, 0], "start_s": 1.0, "reached_s": 4.0,
         "end_s": 9.0, "residual": [0] * 8},
        {"name": "dBx/dy", "U": [0, 0, 0, 0, 100, 0, 0, 0], "start_s": 9.0, "reached_s": 12.0,
         "end_s": 17.0, "residual": [0] * 8},
    ],
}
COMPONENTS = ("Bx", "By", "Bz", "dBx/dx", "dBx/dy", "dBx/dz", "dBy/dy", "dBy/dz")


def test_a_dual_epm_record_draws_fields_gradients_and_both_arms(tmp_path):
    from rigctl.physics.magnetics import U_COMPONENTS

    assert tuple(U_COMPONENTS) == COMPONENTS  # the series' column names follow these
    record = RunRecord(tmp_path, DEPM_PLAN["name"])
    record.write_file("plan.json", json.dumps(DEPM_PLAN))
    joints = [Channel(f"{arm}_q{j}", "rad", -lim, lim, arm)
              for arm in ("left", "right") for j, lim in ((1, 2.96706), (2, 2.094395))]
    record.open_stream(joints, rate_hz=25.0)
    units = {"t_plan_s": "s", "seq": "", **{f"B1{a}_mT": "mT" for a in "xyz"},
             **{f"U_{c}": "mT" if i < 3 else "mT/m" for i, c in enumerate(COMPONENTS)}}
    field = record.open_series("field", list(units), units)
    record.event("segment", name="Bx", t_plan_s=1.0)
    for k in range(20):
        record.stream_row(k, 0, [0.1 * k] * 4, [0.1 * k - 0.01] * 4, period_error_s=2e-4)
        t_plan = float(k)
        u = [10.0 if 4 <= t_plan < 9 else 0.0, 0, 0, 0, 100.0 if t_plan >= 12 else 0.0, 0, 0, 0]
        field.row([t_plan, k, 0.0, 0.0, 1.0, *u])
        if k == 9:
            record.event("segment", name="dBx/dy", t_plan_s=9.0)
        if k == 15:
            record.event("fault", device="left", reason="left: joint A2 stalled")
    record.finish({"reached": False, "state": "faulted", "safe": True, "unsafe_devices": [],
                   "rig": "depm", "plan_kind": "field-sequence", "agents": [],
                   "faults": [{"device": "left", "reason": "left: joint A2 stalled"}],
                   "replans": 0, "tracking": None, "stream": None, "metrics": {}})
    events = read_events(record.path)
    (t0, p0), (t1, p1) = [(e["t"], e["t_plan_s"]) for e in events if e["event"] == "segment"]
    fault_t = next(e["t"] for e in events if e["event"] == "fault")
    fault_on_plan_clock = p0 + (fault_t - t0) * (p1 - p0) / (t1 - t0)

    fig = build_figure(record.path)
    assert sorted(ax.get_gid() for ax in fig.axes) == [
        "actuators:left", "actuators:right", "fields", "gradients", "period"]
    fields, gradients = by_gid(fig, "fields"), by_gid(fig, "gradients")
    assert fields.get_ylabel() == "field (mT)" and gradients.get_ylabel() == "gradient (mT/m)"
    # the requests: each segment's U while it holds (reached_s to end_s)
    (bx,) = lines(fields, "requested Bx")
    np.testing.assert_allclose(bx.get_xdata(), [4.0, 9.0, np.nan, 12.0, 17.0, np.nan])
    np.testing.assert_allclose(bx.get_ydata(), [10, 10, np.nan, 0, 0, np.nan])
    (dxy,) = lines(gradients, "requested dBx/dy")
    np.testing.assert_allclose(dxy.get_ydata(), [0, 0, np.nan, 100, 100, np.nan])
    (measured,) = lines(fields, "measured Bx")
    assert max(measured.get_ydata()) == 10.0 and len(measured.get_xdata()) == 20
    for side in ("left", "right"):
        arm = by_gid(fig, f"actuators:{side}")
        assert arm.get_ylabel() == "joint angle (rad)"
        assert sorted({line.get_ydata()[0] for line in lines(arm, "limit")}) == pytest.approx(
            [-2.96706, -2.094395, 2.094395, 2.96706])
    for ax in fig.axes:  # every panel on the plan's clock, the fault at its place on it
        assert ax.get_xlabel() in ("", "plan time (s)")
        (fault,) = lines(ax, "fault")
        assert fault.get_xdata()[0] == pytest.approx(fault_on_plan_clock)


def test_an_old_dual_epm_record_draws_from_its_csv_files(tmp_path):
    """Records from before channels: `field.csv` and `joints.csv`, both on the plan's clock,
    the joints' limits those of the LBR iiwa 14 (+-170, 120, 170, 120, 170, 120, 175 deg)."""
    run_dir = tmp_path / "20260101T000000.000000Z-old"
    run_dir.mkdir()
    (run_dir / "plan.json").write_text(json.dumps(DEPM_PLAN))
    (run_dir / "events.jsonl").write_text(json.dumps({"t": 0.1, "event": "connected"}) + "\n")
    header = ["t_s", "seq", "B1x_mT", *(f"U_{c}" for c in COMPONENTS)]
    rows = [[k * 0.5, k, 0.0, *([1.0] * 8)] for k in range(10)]
    (run_dir / "field.csv").write_text(",".join(header) + "\n" + "\n".join(
        ",".join(str(x) for x in row) for row in rows) + "\n")
    names = [f"{kind}_{arm}_q{j}" for arm in ("left", "right") for kind in ("cmd", "meas")
             for j in range(1, 8)]
    (run_dir / "joints.csv").write_text("t_s," + ",".join(names) + "\n" + "\n".join(
        ",".join([str(k * 0.5)] + ["0.5"] * len(names)) for k in range(10)) + "\n")

    fig = build_figure(run_dir)
    assert sorted(ax.get_gid() for ax in fig.axes) == [
        "actuators:left", "actuators:right", "fields", "gradients"]
    limits = np.radians([170, 120, 175])
    arm = by_gid(fig, "actuators:left")
    assert sorted({line.get_ydata()[0] for line in lines(arm, "limit")}) == pytest.approx(
        sorted([*limits, *-limits]))
    assert "no stream timing" in figure_text(fig)
    assert "did not finish" in figure_text(fig)  # no summary


def test_a_record_cut_off_before_the_stream_draws_only_what_it_has(tmp_path):
    record = RunRecord(tmp_path, "cut")
    record.write_file("plan.json", json.dumps(GLOBAL_PLAN))
    record.event("prepared", rate_hz=100.0)
    record.close()  # a crash: no stream, no summary
    fig = build_figure(record.path)
    assert [ax.get_gid() for ax in fig.axes] == ["paths"]  # no empty actuator panel
    text = figure_text(fig)
    assert "no actuator stream" in text and "no measured positions" in text
    assert "did not finish" in text
    paths = by_gid(fig, "paths")
    assert not lines(paths, "measured 0")  # nothing measured, nothing drawn


def _stream_only_record(tmp_path, rig: str, channels: list, rig_toml: str | None = None):
    """A record of `rig` with a short stream of `channels` and nothing else (no plan paths)."""
    record = RunRecord(tmp_path, f"{rig} stream")
    record.write_file("plan.json", json.dumps({"schema": "rigctl.plan/1", "name": "stream only",
                                               "kind": "hold", "rig": rig}))
    if rig_toml is not None:
        record.write_file("rig.toml", rig_toml)
    record.open_stream(channels, rate_hz=100.0)
    for k in range(10):
        values = [float(k + j) for j in range(len(channels))]
        record.stream_row(k, 0, values, values)
    record.finish({"state": "done", "rig": rig, "faults": []})
    return record.path


def test_a_panel_title_is_the_rig_kinds_own_and_a_kind_not_installed_gets_its_group(
        global_moves_record, tmp_path):
    currents = by_gid(build_figure(global_moves_record[0]), "actuators:supplies")
    assert currents.get_title().startswith("coil currents (six supplies):")
    # a record of a rig kind not installed here still draws, its panel titled by its group
    run_dir = _stream_only_record(tmp_path, "spinner", [Channel("m1", "A", -2.0, 2.0, "driver")])
    panel = by_gid(build_figure(run_dir), "actuators:driver")
    assert panel.get_title().startswith("driver:")
    assert sorted({line.get_ydata()[0] for line in lines(panel, "limit")}) == [-2.0, 2.0]


def test_an_old_coil_board_record_draws_its_amps_as_the_boards_drive_values(tmp_path):
    """Coil-board records from before channels had units wrote the SyRen drive values as amps
    with no limit and no group: drawn as the board's drive, limited by its rig file's
    max_command."""
    run_dir = _stream_only_record(tmp_path, "coil-board", ["c0", "c1", "c2", "c3"],
                                  rig_toml="[board]\nmax_command = 90\n")
    board = by_gid(build_figure(run_dir), "actuators:board")
    assert board.get_title().startswith("coil board drive (SyRen):")
    assert board.get_ylabel() == "SyRen drive (-127..127)"
    assert sorted({line.get_ydata()[0] for line in lines(board, "limit")}) == [-90.0, 90.0]
    (measured,) = lines(board, "measured c3")
    np.testing.assert_allclose(measured.get_ydata(), np.arange(10) + 3.0)
