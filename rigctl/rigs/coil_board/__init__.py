"""The Arduino coil board (seed 004): two particles placed by wall contacts, closed loop."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.rigs.base import Device, RigKind, camera_devices
from rigctl.rigs.coil_board.faults import fault_profile
from rigctl.rigs.coil_board.report import REPORT

if TYPE_CHECKING:
    from rigctl.rigs.coil_board.settings import CoilBoardRig



def _own(rig: RigConfig) -> CoilBoardRig:
    """`rig` as this kind's rig file model (imported when a hook runs, not when the kind loads)."""
    from rigctl.rigs.coil_board.settings import coil_board_rig

    return coil_board_rig(rig)

def _global_moves(plan, rig: RigConfig, **run):
    """Always closed loop (no `closed_loop` option): a move ends when the camera sees it done."""
    from rigctl.rigs.coil_board.run import CoilBoardRun

    rig = _own(rig)
    return CoilBoardRun(plan, rig, **run)


def _bench_rig() -> RigConfig:
    """The rig `rigctl emulate coil-board` serves, as a plan's checks see it before the bench
    starts (its links' addresses are the bench's to choose then): the board's settings and a
    camera calibrated over the bench's field (`rigctl.emulators.coilboard.bench`)."""
    from rigctl.core.config import CameraSettings, CoilBoardSettings, Emulation, RigInfo
    from rigctl.emulators.camera import PAPER_RESOLUTION, CameraModel
    from rigctl.emulators.coilboard.bench import BOARD_REPLY_TIMEOUT_S, CAMERA_FIELD_MM, CAMERA_FPS
    from rigctl.rigs.coil_board.settings import CoilBoardRig

    camera = CameraSettings(url="http://127.0.0.1/stream.mjpg", stamped=True, fps=CAMERA_FPS,
                            resolution=PAPER_RESOLUTION, calibration=CameraModel.overhead(
                                CAMERA_FIELD_MM, tilt_deg=4.0).calibration())  # as it mounts it
    return CoilBoardRig(rig=RigInfo(kind="coil-board", name="emulated coil-board bench"),
                     board=CoilBoardSettings(url="/dev/null", reply_timeout_s=BOARD_REPLY_TIMEOUT_S),
                     camera=camera, emulation=Emulation(backdoor="tcp://127.0.0.1:1"))


def _channels(rig: RigConfig) -> list[Channel]:
    from rigctl.rigs.coil_board.actuators import board_channels

    rig = _own(rig)
    return board_channels(rig)


def _devices(rig: RigConfig) -> list[Device]:
    rig = _own(rig)
    board = [Device("coil board", rig.board.url, "board")] if rig.board is not None else []
    return board + camera_devices(rig)


def _make_safe(rig: RigConfig) -> dict[str, str | None]:
    """Every coil off (STOP, acknowledged with all outputs zero); the board's own 200 ms link
    watchdog zeroes them anyway once nobody talks to it."""
    from rigctl.core.errors import RigError
    from rigctl.drivers.coilboard import CoilBoard

    rig = _own(rig)
    if rig.board is None:
        return {}
    try:
        board = CoilBoard.from_settings(rig.board)
        try:
            ack = board.stop()
        finally:
            board.close()
        outputs = list(getattr(ack, "outputs", []) or [])
        if any(outputs):
            return {"coil board": f"STOP acknowledged with outputs {outputs}"}
        return {"coil board": None}
    except RigError as err:
        return {"coil board": str(err)}


def _hold(rig: RigConfig, target: dict):
    """`{"drive": [v per coil]}`: whole SyRen drive units within the board's +-max_command, in the
    order of the board's coils (the pull's sense); ramps pass only through values between."""
    from rigctl.core.errors import ConfigError, LimitError
    from rigctl.rigs.coil_board.actuators import BoardActuators
    from rigctl.run.hold import HoldRequest, target_values

    rig = _own(rig)
    board = rig.board
    if board is None:
        raise ConfigError("the rig has no [board] table: it is not a coil board")
    names = list(board.coil_names)
    drive = target_values(target, "drive", (len(names),), KIND.name,
                          f"SyRen drive units for coils {', '.join(names)}")
    for name, value in zip(names, drive):
        if value != round(value):
            raise LimitError(f"coil {name}: drive {value:g} is not a whole SyRen unit; ask for "
                             f"an integer in -{board.max_command}..{board.max_command}")
        if abs(value) > board.max_command:
            raise LimitError(f"coil {name}: drive {value:g} is beyond the board's limit "
                             f"+-{board.max_command}; ask for less")
    return HoldRequest({"drive": drive.tolist()}, drive, BoardActuators.connect, board.rate_hz,
                       "slip", lambda start, ramp_s: None, step=1.0)


def _teleop(rig: RigConfig, mode: str | None):
    from rigctl.rigs.coil_board.teleop import teleop_drive

    rig = _own(rig)
    return teleop_drive(rig, mode)


def _settings() -> type[RigConfig]:
    from rigctl.rigs.coil_board.settings import CoilBoardRig

    return CoilBoardRig



def _probe_board(rig: RigConfig, device: Device) -> str:
    from rigctl.rigs.coil_board.probes import board

    rig = _own(rig)
    return board(rig, device)


def _windings(rig: RigConfig):
    """The board's four coils, each driven by a SyRen in drive units (a voltage)."""
    from rigctl.physics.thermal import Windings

    rig = _own(rig)
    return Windings.of_board(rig.board)


def _patience_s(rig: RigConfig) -> float:
    """A request's retries and a reconnect after an unplug, the board's driver's own patience."""
    board = _own(rig).board
    assert board is not None  # CoilBoardRig's check
    return board.reconnect_s + (board.retries + 1) * board.reply_timeout_s


def _template() -> str:
    """The commented rig file of `rigctl init coil-board` (package data)."""
    from importlib.resources import files

    return (files("rigctl.rigs.coil_board") / "template.toml").read_text()

def _plan_goals(rig: RigConfig, problem):
    """Clicked goals for two particles: seed 004's wall-contact planner; the global-input RRT on
    non-slip walls for a workspace it does not plan in (obstacles, not two particles)."""
    from rigctl.plans.goals import plan_rrt_goals, plan_wall_contact_goals

    document = problem.workspace
    if len(problem.starts_mm) == 2 and "boundary" in document and not document.get("obstacles"):
        return plan_wall_contact_goals(problem)
    return plan_rrt_goals(problem, "non-slip")


KIND = RigKind(
    teleop=_teleop,
    plan_goals=_plan_goals,
    wall_contact="non-slip",
    name="coil-board",
    description="an Arduino driving four SyRen motor drivers on iron-core coils, overhead camera",
    faults=fault_profile,
    report=REPORT,
    plans={"global-moves": _global_moves},
    channels=_channels, devices=_devices, make_safe=_make_safe, hold=_hold, bench_rig=_bench_rig, settings=_settings,
    template=_template, bench="rigctl.emulators.coilboard.bench:CoilBoardBench",
    probes={"board": _probe_board}, windings=_windings, patience_s=_patience_s)
