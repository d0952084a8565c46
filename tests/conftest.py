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

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def prefect_harness():
    """One Prefect test server for the whole session (DESIGN.md: about 10-13 s)."""
    from prefect.testing.utilities import prefect_test_harness
    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture(scope="session")
def tiny_mission(tmp_path_factory):
    """A simulated ``tiny`` mission (seed 1) with its truth; shared, treat as read-only."""
    from swathflow.sensors.pendulum.simulate import simulate
    out = tmp_path_factory.mktemp("tiny") / "mission"
    simulate(out, preset="tiny", seed=1)
    return out
