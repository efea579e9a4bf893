"""`rigctl status` prints whatever shape of `status` its owner answers: the daemon's, a local
run's, or a local run of an older rigctl whose `run` had no `sample` (it printed `state: running`
and then a traceback, `KeyError: 'sample'`)."""

from __future__ import annotations

from rigctl.apps.cli.daemon import _status_text


def test_rigctl_status_prints_a_reply_without_the_keys_it_knows():
    older_local = {"state": "running", "reason": None, "device": None, "owner": "rigctl execute",
                   "rig": {"name": "bench", "kind": "six-coil", "emulated": True},
                   "devices": [{"name": "x+", "url": "tcp://127.0.0.1:5025", "kind": "supply",
                                "health": "ok", "detail": "in use by rigctl execute"}],
                   "run": {"name": "fig4", "moves": 2, "samples": 900, "duration_s": 4.5},
                   "last_fault": None}
    assert _status_text(older_local).splitlines() == [
        "state: running; owner: rigctl execute", "rig: bench (six-coil, emulated)",
        "run: fig4 sample ?/900 move ?/2",
        "  x+   ok       tcp://127.0.0.1:5025  in use by rigctl execute"]


def test_rigctl_status_prints_the_daemons_reply():
    daemon = {"state": "faulted", "device": "y+", "reason": "link down",
              "rig": {"name": "lab", "kind": "six-coil", "emulated": False},
              "run": {"kind": "plan", "id": "2026-run", "plan_id": "abc", "sample": 10,
                      "samples": 900, "move": 0, "moves": 2, "duration_s": 4.5},
              "devices": [], "last_fault": {"device": "y+", "reason": "link down"},
              "hold": None}
    assert _status_text(daemon).splitlines() == [
        "state: faulted (y+: link down)", "rig: lab (six-coil)",
        "run: 2026-run plan abc sample 10/900 move 1/2", "last fault: y+: link down"]
