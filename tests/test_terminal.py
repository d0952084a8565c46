"""The terminal: --quiet/--verbose on every command, rich progress bars on a terminal and
silence elsewhere (checked under a real pseudo-terminal and a pipe), and Prefect's telemetry
notice off by default."""
import os
import pty
import select
import subprocess
import sys

import pytest

from swathflow.flows.cli.main import build_parser


def _subcommands():
    p = build_parser()
    action = next(a for a in p._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


@pytest.mark.parametrize("name", sorted(_subcommands()))
def test_every_command_takes_quiet_and_verbose(name):
    sub = _subcommands()[name]
    opts = {o for a in sub._actions for o in a.option_strings}
    assert {"-q", "--quiet", "-v", "--verbose"} <= opts, name
    with pytest.raises(SystemExit):
        build_parser().parse_args([name, "--quiet", "--verbose"])   # exclusive


def _run_pty(code: str, env: dict, timeout: float = 120.0) -> str:
    """Run ``python -c code`` with stdout and stderr on a fresh pseudo-terminal."""
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=slave, stdout=slave,
                            stderr=slave, env=env, close_fds=True)
    os.close(slave)
    out = b""
    while True:
        ready, _, _ = select.select([master], [], [], timeout)
        if not ready:
            proc.kill()
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:          # the child closed the terminal
            break
        if not chunk:
            break
        out += chunk
    proc.wait(timeout=timeout)
    os.close(master)
    return out.decode("utf-8", "replace")


PROGRESS = """
import sys
from swathflow.flows.progress import Progress, set_verbosity
set_verbosity(int(sys.argv[1]) if len(sys.argv) > 1 else {level})
with Progress() as p:
    p.start("rectify", 3)
    for i in range(3):
        p.update("rectify", i + 1, 3)
    p.finish("rectify", 3)
print("timings", sorted(p.timings))
"""


def _env(**extra):
    env = {k: v for k, v in os.environ.items()
           if k not in ("CI", "DO_NOT_TRACK", "FORCE_COLOR", "NO_COLOR", "TTY_COMPATIBLE")}
    env.update(TERM="xterm-256color", COLUMNS="100", **extra)
    return env


def test_progress_bars_on_a_terminal_and_quiet_elsewhere():
    tty = _run_pty(PROGRESS.format(level=0), _env())
    assert "rectify" in tty and "3/3" in tty and "━" in tty, tty     # a rich bar
    piped = subprocess.run([sys.executable, "-c", PROGRESS.format(level=0)], env=_env(),
                           capture_output=True, text=True, timeout=120, check=True)
    assert piped.stderr == "" and piped.stdout.strip() == "timings ['rectify']"
    verbose = subprocess.run([sys.executable, "-c", PROGRESS.format(level=1)], env=_env(),
                             capture_output=True, text=True, timeout=120, check=True)
    assert "rectify: started (3)" in verbose.stderr and "rectify: done in" in verbose.stderr
    assert "━" not in verbose.stderr
    quiet = _run_pty(PROGRESS.format(level=-1), _env())
    assert "━" not in quiet and "3/3" not in quiet and "timings ['rectify']" in quiet


def test_quiet_command_prints_nothing(tmp_path):
    base = [sys.executable, "-m", "swathflow.flows.cli", "simulate", "--preset", "tiny",
            "--geometry-only"]
    loud = subprocess.run(base + [str(tmp_path / "a")], capture_output=True, text=True,
                          timeout=300, env=_env(), check=True)
    assert "wrote" in loud.stdout
    quiet = subprocess.run(base + [str(tmp_path / "b"), "--quiet"], capture_output=True,
                           text=True, timeout=300, env=_env(), check=True)
    assert quiet.stdout == "" and quiet.stderr == ""
    assert (tmp_path / "b" / "mission.toml").exists()


def test_prefect_telemetry_notice_off_by_default(tmp_path):
    """A new Prefect user on an interactive terminal: importing Prefect alone prints the
    telemetry notice; swathflow's command line sets DO_NOT_TRACK first, so it does not;
    importing swathflow's flow from Python changes no setting (the user's Prefect as is)."""
    def fresh(name):
        home = tmp_path / name
        home.mkdir()
        return _env(PREFECT_HOME=str(home), HOME=str(home))
    bare = _run_pty("import prefect", fresh("bare"))
    assert "anonymous usage data" in bare, bare          # the notice the default hides
    ours = _run_pty("from swathflow.flows.cli import main; main(['sensors']); "
                    "import swathflow.flows.mission, os; print('DNT', os.environ['DO_NOT_TRACK'])",
                    fresh("ours"))
    assert "DNT 1" in ours and "anonymous usage data" not in ours, ours
    imported = _run_pty("import swathflow.flows.mission, os; "
                        "print('DNT', os.environ.get('DO_NOT_TRACK'))", fresh("api"))
    assert "DNT None" in imported and "anonymous usage data" in imported, imported
    opted_in = _run_pty("from swathflow.flows.cli import main; main(['sensors']); "
                        "import swathflow.flows.mission", {**fresh("optin"), "DO_NOT_TRACK": "0"})
    assert "anonymous usage data" in opted_in, opted_in  # the user's choice is kept
