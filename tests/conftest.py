"""Shared test settings: quiet, self-contained Prefect and Dask (DESIGN.md)."""
import os
import sys
import tempfile
from pathlib import Path

_home = tempfile.mkdtemp(prefix="swathflow-prefect-")
os.environ.setdefault("PREFECT_HOME", _home)
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_UI_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "60")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")

# tests import their helper modules (spec_vectors) by plain name
sys.path.insert(0, str(Path(__file__).parent))
