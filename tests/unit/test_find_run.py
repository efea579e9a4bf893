"""`rigctl report RUN`: a run named by path, id, unique prefix or `latest`."""

from __future__ import annotations

import pytest

from rigctl.apps.report import find_run
from rigctl.core.errors import ConfigError


@pytest.fixture
def runs(tmp_path):
    for name in ("20261201T100000Z-a", "20261201T110000Z-b", "20261202T090000Z-c"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "events.jsonl").write_text("")
    (tmp_path / "20261203T000000Z-not-a-run").mkdir()  # no events: not a record
    return tmp_path


def test_latest_is_the_newest_record(runs):
    assert find_run("latest", runs) == runs / "20261202T090000Z-c"


def test_a_unique_prefix_names_its_run(runs):
    assert find_run("20261202", runs) == runs / "20261202T090000Z-c"
    assert find_run(runs / "20261201T100000Z-a", runs) == runs / "20261201T100000Z-a"


def test_an_ambiguous_or_unknown_prefix_says_so(runs):
    with pytest.raises(ConfigError, match="start of 2 runs"):
        find_run("20261201", runs)
    with pytest.raises(ConfigError, match="no run record"):
        find_run("2025", runs)
    with pytest.raises(ConfigError, match="no run record"):
        find_run("latest", runs / "missing")
