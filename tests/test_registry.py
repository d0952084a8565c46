"""The sensor registry with a real installed plugin package (entry points, no patching)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from swathflow.sensors import get_sensor, list_sensors
from swathflow.errors import SwathflowError

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "tests" / "plugins" / "sample"
MIRROR = ROOT / "plugins" / "rotating-mirror"


def _install(folder, target):
    """pip-install a plugin package from its folder into ``target`` (offline, no deps)."""
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--no-build-isolation", "--no-index", "--target", str(target),
                    str(folder)], check=True, capture_output=True, text=True)
    return target


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory):
    return _install(SAMPLE, tmp_path_factory.mktemp("site"))


def _run(site, code):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-W", "always", "-c", code], env=env,
                          capture_output=True, text=True, timeout=120)


def test_builtins_registered():
    assert "pendulum" in list_sensors()
    assert get_sensor("pendulum").name == "pendulum"


def test_unknown_sensor_is_a_clear_error():
    with pytest.raises(SwathflowError, match="unknown sensor model 'nope'.*pendulum"):
        get_sensor("nope")


def test_installed_plugin_is_found_and_broken_ones_warn(plugin_site):
    r = _run(plugin_site, "import json; from swathflow.sensors import list_sensors;"
                          "print(json.dumps({k: v.__module__ for k, v in list_sensors().items()}))")
    assert r.returncode == 0, r.stderr
    found = json.loads(r.stdout.strip().splitlines()[-1])
    assert found["sample-nadir"] == "swathflow_sample_plugins"
    assert found["pendulum"] == "swathflow.sensors.pendulum.model"    # the clash did not replace it
    assert "sample-broken" not in found and "sample-notamodel" not in found
    assert "sample-broken" in r.stderr and "failed to load" in r.stderr
    assert "not a SensorModel" in r.stderr
    assert "clashes" in r.stderr


def test_plugin_passes_contract_suite_and_cli_lists_it(plugin_site):
    r = _run(plugin_site, "from swathflow_sample_plugins import SampleNadirModel as M;"
                          "from swathflow.testing import check_model;"
                          "check_model(M.example_model()); print('contract ok')")
    assert r.returncode == 0 and "contract ok" in r.stdout, r.stderr
    r = _run(plugin_site, "import sys; from swathflow.flows.cli import main; sys.exit(main(['sensors']))")
    assert r.returncode == 0, r.stderr
    assert "sample-nadir" in r.stdout and "pendulum" in r.stdout


@pytest.mark.parametrize("name", sorted(list_sensors()))
def test_every_registered_model_passes_the_contract(name):
    from swathflow.testing import check_model
    cls = get_sensor(name)
    if not hasattr(cls, "example_model"):
        pytest.fail(f"{name} has no example_model() for the contract suite")
    check_model(cls.example_model())


def test_rotating_mirror_example_installs_and_passes_the_contract(tmp_path):
    """The third-party example (plugins/rotating-mirror) installs from its folder with pip,
    appears in `swathflow sensors`, and the contract suite passes for every model."""
    site = _install(MIRROR, tmp_path / "site")
    r = _run(site, "import sys; from swathflow.flows.cli import main; sys.exit(main(['sensors']))")
    assert r.returncode == 0, r.stderr
    assert "rotating-mirror" in r.stdout and "swathflow_rotating_mirror" in r.stdout
    r = _run(site, "import sys; from swathflow.testing import main; sys.exit(main())")
    assert r.returncode == 0, r.stdout + r.stderr
    for name in ("pendulum", "pushbroom", "rotating-mirror"):
        assert f"{name}: ok" in r.stdout
