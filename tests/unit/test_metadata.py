"""The package says what it is: its version where Python and the CLI look, its licence where pip
puts it."""

from importlib.metadata import distribution

import rigctl
from rigctl.apps.cli.main import build_parser


def test_the_version_is_the_installed_distributions(capsys):
    dist = distribution("rigctl")
    assert rigctl.__version__ == dist.version
    try:
        build_parser().parse_args(["--version"])
    except SystemExit as end:
        assert end.code == 0
    assert capsys.readouterr().out.strip() == f"rigctl {dist.version}"


def test_the_licence_is_bsd_3_clause_and_ships_with_the_package():
    dist = distribution("rigctl")
    assert dist.metadata["License-Expression"] == "BSD-3-Clause"
    licence = [f for f in dist.files if f.name == "LICENSE"]
    assert licence, "LICENSE is not among the installed files"
    assert "Redistribution and use in source and binary forms" in licence[0].read_text()


def test_the_version_is_answered_before_any_command_module_loads():
    """`rigctl --version` answers from the package's metadata alone: the parser and the commands'
    modules (numpy, pydantic, OpenCV: half a second) are not imported for it."""
    import subprocess
    import sys

    code = ("import sys; from rigctl.apps.cli import main; code = main(['--version']); "
            "print(code, [m for m in ('rigctl.apps.cli.main', 'numpy', 'pydantic') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == [f"rigctl {distribution('rigctl').version}", "0 []"]
