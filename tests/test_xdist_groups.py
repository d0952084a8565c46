"""The parallel test run's groups hold (tests/conftest.py): under ``pytest -n 2 --dist
loadgroup`` every test of a module runs on one worker, and all the modules that use the
Prefect test server run on one worker together. pytest-xdist 3.8 lost the groups silently
under pytest 9 (each test was scheduled on its own); this runs this directory's conftest on
three small modules in a subprocess and reads which worker ran each test."""
import re
import shutil
import subprocess
import sys
from pathlib import Path



MODULE = '''
import pytest

{fixture}

@pytest.mark.parametrize("i", range(6))
def test_it(i{arg}):
    pass
'''
# a stand-in for the conftest's Prefect server: the group follows the fixture's name
PREFECT = '''
@pytest.fixture
def prefect_harness():
    yield
'''


def test_modules_and_the_prefect_modules_each_run_on_one_worker(tmp_path):
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_plain.py").write_text(MODULE.format(fixture="", arg=""))
    for name in ("test_flow_a", "test_flow_b"):
        (tmp_path / f"{name}.py").write_text(MODULE.format(fixture=PREFECT,
                                                           arg=", prefect_harness"))
    run = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup",
                          "-v", "-p", "no:cacheprovider", "."],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    ran = re.findall(r"\[(gw\d+)\] \[ *\d+%\] PASSED (test_\w+)\.py::test_it\[\d\](\S*)",
                     run.stdout)
    assert len(ran) == 18, run.stdout[-2000:]
    workers = {}
    for worker, module, suffix in ran:            # the node id ends in "@group"
        group = "prefect" if module.startswith("test_flow") else module
        assert suffix == "@" + group, f"{module}: {suffix!r}, not in group {group!r}"
        workers.setdefault(group, set()).add(worker)
    assert set(workers) == {"prefect", "test_plain"}
    assert all(len(w) == 1 for w in workers.values()), workers
