"""Scheduled processing of an inbox: every mission folder that has arrived (it holds a
``mission.toml``) and has no finished output yet is run through the mission flow.

The deployment in ``deploy/prefect.yaml`` runs this on a cron schedule (shipped inactive:
deploy/README.md says how to point it at real folders and switch it on).

Honest outcomes: a missing or unreadable inbox fails the run with a message naming the
folder; a mission that fails is reported and the others still run, and then the run ends
Failed with every failed mission and its reason in the state message. A later run (the
next schedule tick, or a manual one after the mission is fixed) retries it; finished
stages are reused.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from prefect import flow, get_run_logger

from swathflow.errors import SwathflowError
from swathflow.flows.mission import mission_flow
from swathflow.io import write_text


def pending(inbox: str, out_root: str) -> list[Path]:
    """Mission folders in ``inbox`` without a ``DONE.json`` in their output folder.

    Raises :class:`SwathflowError` when ``inbox`` is missing, not a folder or unreadable:
    a schedule pointed at the wrong place must not look like an empty inbox."""
    root = Path(inbox)
    if not root.exists():
        raise SwathflowError(f"inbox folder {root} does not exist: create it or set the "
                             f"deployment's 'inbox' parameter to the folder missions arrive in")
    if not root.is_dir():
        raise SwathflowError(f"inbox {root} is not a folder: set the deployment's 'inbox' "
                             f"parameter to the folder missions arrive in")
    try:
        if not os.access(root, os.R_OK | os.X_OK):
            raise PermissionError(f"no read permission on {root}")
        entries = sorted(root.iterdir())
    except OSError as exc:
        raise SwathflowError(f"inbox folder {root} cannot be read ({exc}): give the worker's "
                             f"user read access to it") from None
    return [p for p in entries
            if (p / "mission.toml").exists() and not (Path(out_root) / p.name / "DONE.json").exists()]


def failure_message(failed: dict[str, str], total: int) -> str:
    """The state message of an inbox run in which missions failed: each one and its reason."""
    lines = "; ".join(f"{name}: {reason}" for name, reason in sorted(failed.items()))
    return (f"{len(failed)} of {total} missions failed ({lines}); fix them and run again "
            f"(finished missions and stages are kept)")


@flow(name="swathflow-inbox")
def inbox_flow(inbox: str, out_root: str, calibration: str | None = None,
               dask_address: str | None = None) -> dict:
    """Process every new mission in ``inbox`` into ``out_root/<mission folder name>``.

    Returns ``{"done": [...], "failed": {}}``; ends Failed (raises :class:`SwathflowError`)
    when the inbox cannot be read or any mission failed.

    Args:
        inbox: The folder new mission folders arrive in (one folder per mission).
        out_root: The folder each mission's products are written under, by its name.
        calibration: A calibration.json to use for every mission instead of calibrating.
        dask_address: The address of a running Dask scheduler to do the heavy work on.
    """
    log = get_run_logger()
    done, failed = [], {}
    todo = pending(inbox, out_root)
    log.info("inbox %s: %d new missions", inbox, len(todo))
    for folder in todo:
        out = Path(out_root) / folder.name
        try:
            result = mission_flow(str(folder), str(out), calibration, dask_address)
        except Exception as exc:  # one bad mission must not stop the others
            reason = " ".join(f"{type(exc).__name__}: {exc}".split())[:600]
            log.error("mission %s failed: %s", folder.name, reason)
            failed[folder.name] = reason
            continue
        write_text(out / "DONE.json", json.dumps(result, indent=2, default=str))
        done.append(folder.name)
        log.info("mission %s done: %s", folder.name, result["mosaic"])
    if failed:
        raise SwathflowError(failure_message(failed, len(todo)))
    return {"done": done, "failed": failed}
