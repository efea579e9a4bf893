"""What the daemon runs: `RunLike` (a run as the daemon drives it), `RunFactory` (what makes
them: the tests' stand-ins, or `PlanRuns`), and `PlanRuns`, plans prepared here at load and
streamed in the stream process (`rigctl.apps.daemon.runhost`)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from rigctl.apps.daemon.runhost import RemoteRun, RunHost
from rigctl.apps.daemon.telemetry import CycleBatch, WindingEstimate
from rigctl.core.config import RigConfig
from rigctl.rigs import prepare_run

MAX_PLANS = 32
"""Plans a daemon keeps loaded (and prepared), the least recently loaded dropped first."""


class RunLike(Protocol):
    """What the daemon needs of a run (`rigctl.rigs.six_coil.global_moves.Run` and the tests' stand-ins)."""

    def execute(self) -> Any: ...
    def pause(self, immediate: bool = False) -> None: ...
    def resume(self) -> None: ...
    def abort(self) -> None: ...
    def estop(self) -> list[str]: ...  # the supplies it could not reach

    plan: Any  # the plan being run (agents, expected)
    info: dict[str, Any]  # what `load` and `status` say of it: name, size, planned duration
    record: Any  # the run record once execute() has made it, else None



class RunFactory(Protocol):
    def start(self) -> None: ...  # when the daemon starts (spawn helpers)
    def close(self) -> None: ...  # when it stops
    def parse_plan(self, data: dict[str, Any]) -> Any: ...

    def prepare(self, plan: Any, rig: RigConfig, *, runs_dir: Path,
                on_cycles: Callable[[CycleBatch], None],
                on_state: Callable[[Any, dict[str, Any]], None]) -> RunLike: ...
    # a run hands its stream cycles to on_cycles in batches (t: time.monotonic())



class PlanRuns:
    """The real thing: plans from `rigctl.plans.schema` (any kind the rig's `RigKind` runs), prepared
    here at load (a bad plan is refused before anything else) and streamed in the stream process
    (`rigctl.apps.daemon.runhost`), which `start` spawns and `close` stops."""

    def __init__(self, realtime_priority: int | None = None, on_frame: Any = None,
                 windings: WindingEstimate | None = None) -> None:
        self.host = RunHost(realtime_priority, on_frame, windings)
        self._lock = threading.Lock()
        # id(plan) -> (plan, the plan as prepared, what load says of it): a plan executed again
        # is not realized and allocated again here (on the command thread) just to be described
        self._checked: OrderedDict[int, tuple[Any, Any, dict[str, Any]]] = OrderedDict()

    def start(self) -> None:
        self.host.start()

    def close(self) -> None:
        self.host.close()

    def parse_plan(self, data: dict[str, Any]) -> Any:
        from rigctl.plans.schema import parse_plan

        return parse_plan(data, "plan")

    def prepare(self, plan: Any, rig: RigConfig, *, runs_dir: Path,
                on_cycles: Callable[[CycleBatch], None],
                on_state: Callable[[Any, dict[str, Any]], None]) -> RunLike:
        """The first time: the run built here refuses a bad plan before anything else happens and
        tells the plan's size. The stream process builds its own from the same prepared plan and
        rig (deterministic, so the same program) and streams that."""
        with self._lock:
            known = self._checked.get(id(plan))
        if known is None or known[0] is not plan:
            # what refuses a plan on a rig (another rig's, a kind it does not run, the rig kind's
            # rules, the pre-flight certificate): the code `rigctl validate` runs
            local = prepare_run(plan, rig, runs_dir=runs_dir)
            certificate = local.certificate
            known = (plan, local.plan, {**local.info, "certificate": {  # its name, size, duration
                "passed": certificate.passed, "checks": len(certificate.checks),
                "rig_sha256": certificate.rig_hash}})
            with self._lock:
                self._checked[id(plan)] = known
                while len(self._checked) > MAX_PLANS:
                    self._checked.popitem(last=False)
        _, prepared, info = known
        return RemoteRun(self.host, ("run", prepared, rig, str(runs_dir)), rig, plan=prepared,
                         info=info, on_cycles=on_cycles, on_state=on_state)

