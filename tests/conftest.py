"""Session set-up shared by every test."""

from __future__ import annotations


def pytest_configure(config) -> None:
    # Compile (or load from numba's on-disk cache) the workspace geometry kernels once, before any
    # test starts an emulator or a re-planning child that would otherwise compile them mid-run.
    from rigctl.plans.workspace import warm_up

    seconds = warm_up()
    if seconds > 1.0:
        print(f"geometry kernels compiled in {seconds:.1f} s (cached for later processes)")
