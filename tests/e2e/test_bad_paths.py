"""Every bad path or file a command takes: one line on stderr naming it, exit 2, no traceback;
with --json the error is the one JSON document on stdout. Also: coordinates such as -8,-6 are
values, options of another rig kind are refused by name, and `rigctl runs` reads as a table."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.apps.cli.execute import refuse_foreign_bench_flags
from rigctl.apps.cli.main import build_parser, main
from rigctl.core.errors import ConfigError

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
PLAN = str(EXAMPLES / "fig4-quick.json")
IMAGE = str(EXAMPLES / "vessel-maze.png")
DISK = str(EXAMPLES / "coilboard-disk.json")
PAIR_WS = str(EXAMPLES / "pair-formation-change-workspace.json")
RRT = ["plan", "rrt", "--workspace", PLAN, "--start", "220,240", "--goal", "250,183"]


@pytest.fixture
def files(tmp_path, monkeypatch):
    """A folder of bad inputs; the tests run in it."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "somedir").mkdir()
    (tmp_path / "afile").write_text("x")
    (tmp_path / "empty.json").write_text("")
    (tmp_path / "latin1.json").write_bytes(b'{"name": "caf\xe9"}')
    (tmp_path / "latin1.toml").write_bytes(b'name = "caf\xe9"\n')
    return tmp_path


# (argv, the path the line must name); "--json" in argv where the command has it
CASES = [
    (["execute", IMAGE, "--json"], IMAGE),
    (["execute", PLAN, "--rig", "somedir", "--json"], "somedir"),
    (["execute", PLAN, "--runs", "afile", "--json"], "afile"),
    (["execute", "missing.json", "--json"], "missing.json"),
    (["execute", "latin1.json", "--json"], "latin1.json"),
    (["execute", "empty.json", "--json"], "empty.json"),
    (["execute", PLAN, "--rig", "latin1.toml", "--json"], "latin1.toml"),
    (["execute", PLAN, "--rig", "empty.json", "--json"], "empty.json"),
    (["execute", PLAN, "--runs", "nodir/runs", "--json"], "nodir/runs"),
    (["report", "latest", "-o", "nodir/x.png"], "nodir/x.png"),
    (["report", "latest", "-o", "somedir"], "somedir"),
    (["report", "latest", "--video", "nodir/x.mp4"], "nodir/x.mp4"),
    (["report", "latest", "--video", "somedir"], "somedir"),
    (["validate", "--simulate", PLAN, "-o", "nodir/x.json"], "nodir/x.json"),
    (["validate", "somedir"], "somedir"),
    (["validate", IMAGE], IMAGE),
    (["emulate", "six-coil", "--rig-out", "nodir/b.toml"], "nodir/b.toml"),
    (["calibrate", "camera", "--rig", "somedir", "--plan", PLAN], "somedir"),
    (["calibrate", "camera", "--rig", "latin1.toml", "--plan", PLAN], "latin1.toml"),
    (["calibrate", "camera", "--rig", "afile", "--plan", IMAGE], IMAGE),
    (["calibrate", "camera", "--rig", "afile", "--plan", PLAN, "-o", "nodir/r.toml"],
     "nodir/r.toml"),
    ([*RRT, "-o", "nodir/p.json", "--json"], "nodir/p.json"),
    (["plan", "rrt", "--workspace", "somedir", "--start", "1,1", "--goal", "2,2", "-o", "p.json",
      "--json"], "somedir"),
    ([*RRT, "--tree", "somedir", "-o", "p.json", "--json"], "somedir"),
    ([*RRT, "--save-tree", "nodir/t.npz", "-o", "p.json", "--json"], "nodir/t.npz"),
    ([*RRT, "--rig-file", "latin1.toml", "-o", "p.json", "--json"], "latin1.toml"),
    (["plan", "coverage", "--workspace", "empty.json", "--tree", "afile", "--grid", "5", "--json"],
     "empty.json"),
    (["plan", "wall-contact", "--workspace", "latin1.json", "--start", "0,0", "--goal", "1,1",
      "-o", "p.json", "--json"], "latin1.json"),
    (["plan", "reachable", "--workspace", "somedir", "--d12", "0.3", "--moves", "2", "--json"],
     "somedir"),
    (["plan", "depm", "--sequence", "missing.json", "-o", "p.json", "--json"], "missing.json"),
    (["plan", "pair", "--workspace", PAIR_WS, "--start", "8,7,2,0", "--goal", "9,7,2,0",
      "--rig", "somedir", "-o", "p.json", "--json"], "somedir"),
    (["plan", "pair", "--workspace", PAIR_WS, "--start", "8,7,2,0", "--goal", "9,7,2,0",
      "-o", "nodir/p.json", "--json"], "nodir/p.json"),
    (["runs", "--runs", "afile", "--json"], "afile"),
    (["runs", "--runs", "nodir", "--json"], "nodir"),
    (["doctor", "--rig", "somedir", "--json"], "somedir"),
    (["estop", "--rig", "latin1.toml"], "latin1.toml"),
    (["pause", "--rig", "empty.json"], "empty.json"),
    (["daemon", "--rig", "somedir"], "somedir"),
    (["watch", "--rig", "somedir"], "somedir"),
    (["status", "--rig", "empty.json", "--json"], "empty.json"),
    (["hold", "--rig", "somedir", "--release"], "somedir"),
    (["load", "missing.json", "--json"], "missing.json"),
    (["status", "--server-key", "afile", "--client-key", "afile", "--json"], "afile"),
]


@pytest.mark.parametrize("argv, path", CASES, ids=[" ".join(Path(a).name for a in c[0][:4])
                                                    for c in CASES])
def test_a_bad_path_is_one_line_and_exit_2(files, capsys, argv, path):
    assert main(argv) == 2
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert path in lines[0] and "Traceback" not in err
    if "--json" in argv:
        document = json.loads(out)  # the one document, nothing else
        assert document["error"]["code"] == "bad_input" and path in document["error"]["message"]
    else:
        assert out == ""


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode")
def test_an_unreadable_rig_file_is_one_line(files, capsys):
    (files / "secret.toml").write_text("x = 1\n")
    (files / "secret.toml").chmod(0)
    assert main(["execute", PLAN, "--rig", "secret.toml"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "secret.toml" in err and "ermission" in err


def test_the_installed_command_prints_no_traceback(files):
    done = subprocess.run([sys.executable, "-m", "rigctl", "execute", IMAGE, "--json"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "not a plan" in done.stderr, done.stderr
    assert json.loads(done.stdout)["error"]["code"] == "bad_input"


# -- negative coordinates -------------------------------------------------------------------------

@pytest.mark.parametrize("spelling", ["separate", "equals"])
def test_negative_coordinates_work_as_written(files, spelling):
    def point(flag, value):
        return [flag, value] if spelling == "separate" else [f"{flag}={value}"]

    argv = ["plan", "wall-contact", "--workspace", DISK, *point("--start", "-8,-6"),
            *point("--goal", "5,5"), *point("--start", "-2,3"), *point("--goal", "-0.5,-4"),
            "-o", "p.json"]
    assert main(argv) == 0
    agents = json.loads(Path("p.json").read_text())["agents"]
    assert [a["start"] for a in agents] == [[-8.0, -6.0], [-2.0, 3.0]]
    assert [a["goal"] for a in agents] == [[5.0, 5.0], [-0.5, -4.0]]


@pytest.mark.parametrize("argv, dest, value", [
    (["plan", "rrt", "--workspace", PLAN, "--start", "-1,-2", "--goal", "3,4", "-o", "p.json"],
     "start", ["-1,-2"]),
    (["plan", "pair", "--start", "-8,-7,2,-90", "--goal", "1,1,2,0"], "start", "-8,-7,2,-90"),
    (["plan", "reachable", "--polygon", "-5,-5;5,-5;0,5", "--d12", "0.3", "--moves", "2"],
     "polygon", "-5,-5;5,-5;0,5"),
    (["calibrate", "camera", "--rig", PLAN, "--markers", "-5,0;5,0;0,-5;0,5"],
     "markers", "-5,0;5,0;0,-5;0,5"),
])
def test_every_coordinate_option_takes_negative_values(files, argv, dest, value):
    assert getattr(build_parser().parse_args(argv), dest) == value


# -- options of another rig kind ------------------------------------------------------------------

@pytest.mark.parametrize("argv, flag, kind", [
    (["execute", PLAN, "--firmware", "simavr", "--json"], "--firmware", "six-coil"),
    (["execute", str(EXAMPLES / "depm-plan.json"), "--slip", "0.8", "--json"], "--slip", "depm"),
    (["execute", str(EXAMPLES / "depm-plan.json"), "--field-at-robots"], "--field-at-robots",
     "depm"),
    (["execute", DISK, "--world", "pair", "--json"], "--world", "coil-board"),
    (["execute", DISK, "--seed", "3"], "--seed", "coil-board"),
    (["emulate", "depm", "--firmware", "simavr"], "--firmware", "depm"),
    (["emulate", "coil-board", "--drift", "0.1"], "--drift", "coil-board"),
    (["emulate", "six-coil", "--firmware", "python"], "--firmware", "six-coil"),
])
def test_an_option_of_another_rig_kind_is_refused_by_name(files, capsys, argv, flag, kind):
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and flag in err and kind in err, err
    if "--json" in argv:
        assert flag in json.loads(out)["error"]["message"]


@pytest.mark.parametrize("kind, options", [
    ("six-coil", ["--slip", "0.8", "--seed", "2", "--field-at-robots", "--world", "pair"]),
    ("coil-board", ["--firmware", "simavr"]), ("depm", ["--seed", "4"])])
def test_the_options_of_a_rig_kind_are_taken(kind, options):
    refuse_foreign_bench_flags(build_parser().parse_args(["emulate", kind, *options]), kind, kind)
    with pytest.raises(ConfigError):  # and the same check does refuse: the others'
        other = "--firmware" if kind != "coil-board" else "--slip"
        refuse_foreign_bench_flags(build_parser().parse_args(
            ["emulate", kind, other, "simavr" if other == "--firmware" else "0.9"]), kind, kind)


# -- rigctl runs ----------------------------------------------------------------------------------

def test_runs_is_a_table_with_a_header_and_rounded_figures(files, capsys):
    run = files / "records" / "20260101T000000.000000Z-demo"
    run.mkdir(parents=True)
    (run / "events.jsonl").write_text("")
    (run / "summary.json").write_text(json.dumps({"reached": True, "faults": [],
                                                  "duration_s": 9.2281}))
    (run / "plan.json").write_text(json.dumps({"name": "demo plan"}))
    assert main(["runs", "--runs", "records"]) == 0
    header, row = capsys.readouterr().out.splitlines()
    assert header.split() == ["RUN", "RESULT", "TIME", "(s)", "PLAN"]
    assert row.split() == [run.name, "reached", "9.2", "demo", "plan"]
    assert main(["runs", "--runs", "records", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["duration_s"] == 9.2281  # machine data as is


def test_runs_says_when_a_folder_has_none(files, capsys):
    assert main(["runs", "--runs", "somedir"]) == 0
    assert capsys.readouterr().out == "no runs in somedir\n"


def test_an_emulated_bench_beyond_loopback_is_served_with_a_warning(tmp_path):
    import subprocess
    import sys

    bench = subprocess.Popen([sys.executable, "-m", "rigctl", "emulate", "six-coil", "--host",
                              "0.0.0.0", "--rig-out", str(tmp_path / "b.toml")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        warning = bench.stderr.readline()
        assert warning.startswith("warning: serving the emulated devices on 0.0.0.0")
        assert "the backdoor takes only the token" in warning
        assert bench.stdout.readline().startswith("READY ")
    finally:
        bench.terminate()
        bench.wait(30)


def test_an_emulated_bench_on_a_host_that_does_not_resolve_is_refused(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "rigctl", "emulate", "six-coil", "--host",
                           "nosuchhost.invalid", "--rig-out", str(tmp_path / "b.toml")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stderr.startswith("error: --host nosuchhost.invalid")


def test_an_endpoint_that_is_not_a_url_is_one_line(capsys):
    assert main(["daemon", "--command", "tcp://[127.0.0.1]:5599"]) == 2  # nothing started
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tcp://[127.0.0.1]:5599" in err and "Traceback" not in err

