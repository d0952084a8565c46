"""Scheduled processing of an inbox: every mission folder that has arrived (it holds a
``mission.toml``) and has no finished output yet is run through the mission flow.

The deployment in ``deploy/prefect.yaml`` runs this on a cron schedule. A mission whose run
fails is reported and retried on the next schedule tick (finished stages are reused).
"""
from __future__ import annotations

import json
from pathlib import Path

from prefect import flow, get_run_logger

from swathflow.flows.mission import mission_flow
from swathflow.io import write_text


def pending(inbox: str, out_root: str) -> list[Path]:
    """Mission folders in ``inbox`` without a ``DONE.json`` in their output folder."""
    root = Path(inbox)
    if not root.is_dir():
        return []
    return [p for p in sorted(root.iterdir())
            if (p / "mission.toml").exists() and not (Path(out_root) / p.name / "DONE.json").exists()]


@flow(name="swathflow-inbox")
def inbox_flow(inbox: str, out_root: str, calibration: str | None = None,
               dask_address: str | None = None) -> dict:
    """Process every new mission in ``inbox`` into ``out_root/<mission folder name>``."""
    log = get_run_logger()
    done, failed = [], {}
    for folder in pending(inbox, out_root):
        out = Path(out_root) / folder.name
        try:
            result = mission_flow(str(folder), str(out), calibration, dask_address)
        except Exception as exc:  # one bad mission must not stop the others
            log.error("mission %s failed: %s", folder.name, exc)
            failed[folder.name] = str(exc)
            continue
        write_text(out / "DONE.json", json.dumps(result, indent=2, default=str))
        done.append(folder.name)
        log.info("mission %s done: %s", folder.name, result["mosaic"])
    return {"done": done, "failed": failed}
