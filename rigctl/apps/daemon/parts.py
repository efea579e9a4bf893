"""What the `Daemon`'s parts (`RequestServer`, `Commands`, `TeleopCommands`, `RunWatch`,
`RunStates`: one class each, by concern) read of one another, for the type checker.

Each part uses the daemon's state and some of the others' methods; `Daemon.__init__` makes the
state and the daemon has every part's methods. `DaemonParts`, every part's base, declares them
for mypy only (under TYPE_CHECKING): at run time it is an empty class, so no declaration here can
stand in front of a part's own method in the daemon's method order."""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zmq

    from rigctl.apps.daemon.admission import Admission
    from rigctl.apps.daemon.keys import CurveServer
    from rigctl.apps.daemon.messages import Command, DaemonState
    from rigctl.apps.daemon.plan_runs import RunFactory, RunLike
    from rigctl.apps.daemon.replay import ReplayCache
    from rigctl.apps.daemon.sdnotify import SystemdNotifier
    from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher
    from rigctl.core.channels import Channel
    from rigctl.core.config import RigConfig
    from rigctl.rigs.base import RigKind


# The parts' own modules import this one: naming their classes here would make an import cycle
# (tools/import_graph.py counts the type checker's imports too), so those are Any, each with the
# class it is named in a comment.
class DaemonParts:
    """The daemon's state and methods its parts share (see the module docstring)."""

    if TYPE_CHECKING:
        rig: RigConfig
        kind: RigKind
        runs_dir: Path
        t0: float
        held: dict[str, Any] | None
        factory: RunFactory
        notifier: SystemdNotifier
        curve: CurveServer | None
        publisher: TelemetryPublisher | None
        endpoints: Any  # DaemonEndpoints | None (server.py)
        state: DaemonState
        _state_info: dict[str, Any]
        last_fault: dict[str, Any] | None
        last_run: dict[str, Any] | None
        _lock: threading.RLock
        _active: Any  # ActiveRun | None (active_run.py)
        _plans: OrderedDict[str, Any]  # _LoadedPlan (commands.py)
        _deliveries: deque[Callable[[], None]]
        _replay: ReplayCache
        _worker: ThreadPoolExecutor
        load_deadline_s: float
        _wakeup: Any  # _Wakeup (requests.py)
        _loading: Any  # _Loading | None (requests.py)
        admission: Admission
        _stop: threading.Event
        _shutdown_requested: threading.Event
        _serving: threading.Event
        _router: zmq.Socket[bytes] | None
        _agents_stop: threading.Event
        _command_priority: int | None
        unsafe: set[str]
        channels: list[Channel]
        devices: dict[str, dict[str, str]]
        goals: Any  # GoalPlanning (goals.py)
        _handlers: dict[Command, Callable[[Any], Any]]

        def _require(self, *states: DaemonState, doing: str) -> None: ...
        def _require_safe(self, doing: str) -> None: ...
        def _transition(self, event: str, **info: Any) -> bool: ...
        def _publish_state(self) -> None: ...
        def _on_cycles(self, batch: CycleBatch) -> None: ...
        def _on_run_state(self, run_state: Any, info: dict[str, Any]) -> None: ...
        def _run_thread(self, active: Any) -> None: ...
        def _device(self, name: str, health: str, detail: str) -> None: ...
        def _sample_agents(self, active: Any) -> None: ...
        def _activate(self, active: Any, event: str) -> None: ...
        def _prepare(self, plan: Any) -> RunLike: ...
        def _shut_down_step(self) -> bool: ...
        def _close(self) -> None: ...
        def _make_safe_directly(self) -> None: ...
