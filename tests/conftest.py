"""Shared test settings: quiet, self-contained Prefect and Dask."""
import os
import sys
import tempfile
from pathlib import Path

# one Prefect home per test process: pytest-xdist's workers inherit the controller's
# environment, and two Prefect servers on one SQLite database lock each other out
if os.environ.get("PREFECT_HOME", "") in ("", os.environ.get("SWATHFLOW_TEST_PREFECT_HOME")):
    os.environ["PREFECT_HOME"] = os.environ["SWATHFLOW_TEST_PREFECT_HOME"] = \
        tempfile.mkdtemp(prefix="swathflow-prefect-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_UI_ENABLED", "false")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "60")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")

# tests import their helper modules (spec_vectors) by plain name
sys.path.insert(0, str(Path(__file__).parent))

import pytest  # noqa: E402


def _xdist_group(item) -> str:
    """The item's pytest-xdist group: its module, or "prefect" for every module that uses
    the Prefect test server."""
    return "prefect" if "prefect_harness" in item.fixturenames else item.module.__name__


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """With pytest-xdist (``--dist loadgroup``): a module's tests stay on one worker (its
    module-scoped fixtures are built once), and every module that uses the Prefect test
    server shares one worker (one server for the session, not one per worker).

    loadgroup sends the tests whose node ids end in the same ``@group`` to one worker; a
    worker's own ``pytest_collection_modifyitems`` appends that suffix from the
    ``xdist_group`` marks. So the marks go on first (this wrapper runs before it), and the
    suffix is checked after it: pytest-xdist 3.8 writes it to ``item._nodeid``, which
    pytest 9 no longer reads (the node id is ``item._id``, a NodeId), so there the groups
    were silently lost and every test was its own group (pytest-xdist issue #1386, open;
    once xdist writes it itself, the suffix is there and this does nothing); this writes it
    where pytest reads it. Nothing happens without pytest-xdist or in the serial run."""
    xdist = config.pluginmanager.hasplugin("xdist")
    if xdist:
        for item in items:
            item.add_marker(pytest.mark.xdist_group(_xdist_group(item)))
    result = yield
    if xdist and getattr(config.option, "loadgroup", False):     # an xdist worker
        for item in items:
            suffix = "@" + _xdist_group(item)
            if not item.nodeid.endswith(suffix) and hasattr(item, "_id"):
                from _pytest.nodeid import NodeId
                item._id = NodeId.parse(item.nodeid + suffix)
    return result


@pytest.fixture(scope="session")
def prefect_harness():
    """One Prefect test server for the whole session (Prefect's own harness, its
    database migrated afresh: 25-45 s on 2 busy cores)."""
    from prefect.testing.utilities import prefect_test_harness
    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture(scope="session")
def tiny_mission(tmp_path_factory):
    """A simulated ``tiny`` mission (seed 1) with its truth; shared, treat as read-only.
    Under pytest-xdist the workers share one copy: the first builds it while the others
    wait (a cold numba cache would otherwise compile the same kernels in every worker)."""
    import fcntl
    from swathflow.sensors.pendulum.simulate import simulate
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent                  # the session's folder, above the workers' own
    out, done = root / "tiny-shared" / "mission", root / "tiny-shared.done"
    with open(root / "tiny-shared.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            simulate(out, preset="tiny", seed=1)
            done.touch()
    return out


def _simulated(tmp_path_factory, name: str, *options) -> Path:
    from swathflow.flows.cli import main
    out = tmp_path_factory.mktemp(name) / "tiny"
    assert main(["simulate", str(out), "--preset", "tiny", "--seed", "3", "--geometry-only",
                 *options]) == 0
    return out


@pytest.fixture(scope="session")
def fault_base(tmp_path_factory) -> Path:
    """The fault suites' mission (tests/test_faults*.py): a simulated ``tiny`` mission,
    geometry only (its images a constant 1000, its control points exact), seed 3; shared,
    treat as read-only (break the copy ``m``)."""
    return _simulated(tmp_path_factory, "faults")


@pytest.fixture(scope="session")
def fault_envi(tmp_path_factory) -> Path:
    """:func:`fault_base` with ENVI raw images; shared, treat as read-only."""
    return _simulated(tmp_path_factory, "faults-envi", "--image-format", "envi")


@pytest.fixture
def m(fault_base, tmp_path) -> Path:
    """A copy of :func:`fault_base` of the test's own, to break."""
    import shutil
    return Path(shutil.copytree(fault_base, tmp_path / "m"))


@pytest.fixture
def m_envi(fault_envi, tmp_path) -> Path:
    """A copy of :func:`fault_envi` of the test's own, to break."""
    import shutil
    return Path(shutil.copytree(fault_envi, tmp_path / "e"))
