"""Prefect tasks: thin wrappers over the maths in :mod:`swathflow`, passing paths and small
metadata. Heavy arrays stay inside a task (Dask over xarray) and go to disk."""
import os as _os

# Prefect's client telemetry and its first-run notice: off unless the environment says
# otherwise (set before the stages import Prefect)
_os.environ.setdefault("DO_NOT_TRACK", "1")
