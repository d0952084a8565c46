"""The command line: help, sensors, and clear errors for bad input."""
import subprocess
import sys

from swathflow.flows.cli import main


def test_help_lists_every_command(capsys):
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out
    for cmd in ("sensors", "validate", "simulate", "calibrate", "rectify", "mosaic", "run", "demo"):
        assert cmd in out


def test_sensors_lists_pendulum(capsys):
    assert main(["sensors"]) == 0
    assert "pendulum" in capsys.readouterr().out


def test_console_script_is_installed():
    r = subprocess.run([sys.executable, "-c", "from importlib.metadata import entry_points;"
                        "print([e.value for e in entry_points(group='console_scripts')"
                        " if e.name == 'swathflow'])"], capture_output=True, text=True)
    assert "swathflow.flows.cli:main" in r.stdout
