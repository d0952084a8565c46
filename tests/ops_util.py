"""Helpers of the operations tests (tests/test_ops_*.py): start and stop the services
through the deploy/ scripts, and check that nothing they started is left running."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def script(path: str, *args: str, env: dict | None = None, timeout: float = 300) -> str:
    """Run a deploy/ script; its stdout, or an assertion naming its output on failure."""
    r = subprocess.run(["bash", str(DEPLOY / path), *args], env=env or dict(os.environ),
                       capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{path} {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r.stdout


def pids_in(folder: Path, *patterns: str) -> dict[str, int]:
    """The PID files in ``folder`` (matching ``patterns``, default ``*.pid``) and their PIDs."""
    files = {p for pat in patterns or ("*.pid",) for p in folder.glob(pat)}
    return {str(p.relative_to(folder)): int(p.read_text().split()[0])
            for p in sorted(files) if p.read_text().strip()}


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is not running
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def listening_on(port: int) -> list[str]:
    """The local addresses listening on TCP ``port`` (from /proc/net/tcp{,6})."""
    found = []
    for name in ("tcp", "tcp6"):
        try:
            rows = Path(f"/proc/net/{name}").read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            local, state = row.split()[1], row.split()[3]
            addr, p = local.split(":")
            if state == "0A" and int(p, 16) == port:
                found.append(addr)
    return found


LOOPBACK_HEX = {"0100007F", "00000000000000000000000001000000"}


def wait_for(condition, timeout: float, failure: str, interval: float = 1.0):
    """Poll ``condition()`` until it returns something truthy and return that; a service
    that never gets there fails the test with ``failure`` (a bound on a wait for a
    service, not a speed requirement)."""
    import time
    end = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"{failure} (waited {timeout:g} s)")
        time.sleep(interval)

