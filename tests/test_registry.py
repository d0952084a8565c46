"""The sensor registry with a real installed plugin package (entry points, no patching)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from swathflow.sensormodel import get_sensor, list_sensors
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
    r = _run(plugin_site, "import json; from swathflow.sensormodel import list_sensors;"
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


def test_rotating_mirror_example_installs_and_passes_the_contract(mirror_site):
    """The third-party example (plugins/rotating-mirror) installs from its folder with pip,
    appears in `swathflow sensors`, and the contract suite passes for every model."""
    site = mirror_site
    r = _run(site, "import sys; from swathflow.flows.cli import main; sys.exit(main(['sensors']))")
    assert r.returncode == 0, r.stderr
    assert "rotating-mirror" in r.stdout and "swathflow_rotating_mirror" in r.stdout
    r = _run(site, "import sys; from swathflow.testing import main; sys.exit(main())")
    assert r.returncode == 0, r.stdout + r.stderr
    for name in ("pendulum", "pushbroom", "rotating-mirror"):
        assert f"{name}: ok" in r.stdout


# --- the rotating-mirror example's own hooks: its line-table column and its simulator ----------
MIRROR_CLI = "import sys; from swathflow.flows.cli import main; sys.exit(main({args!r}))"


def _cli(site, *commands):
    """Run swathflow commands one after the other in one process (one start-up); returns
    the completed process and the exit code of every command."""
    code = ("import json; from swathflow.flows.cli import main\n"
            f"codes = [main(a) for a in {[list(c) for c in commands]!r}]\n"
            "print('EXIT CODES', json.dumps(codes))")
    r = _run(site, code)
    assert r.returncode == 0 and "EXIT CODES" in r.stdout, r.stdout + r.stderr
    return r, json.loads(r.stdout.rsplit("EXIT CODES", 1)[1])


@pytest.fixture(scope="module")
def mirror_site(tmp_path_factory):
    return _install(MIRROR, tmp_path_factory.mktemp("mirror-site"))


@pytest.fixture(scope="module")
def mirror_mission(mirror_site, tmp_path_factory):
    """``swathflow simulate OUT --preset rotating-mirror`` with the plugin pip-installed:
    the preset comes from the plugin's ``simulator()`` hook."""
    out = tmp_path_factory.mktemp("mirror") / "mission"
    r = _run(mirror_site, MIRROR_CLI.format(args=["simulate", str(out), "--preset",
                                                  "rotating-mirror", "--seed", "1"]))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 images" in r.stdout and "rendered" in r.stdout
    return out


def _mirror_vs_truth(rect_dir, mission):
    """Shift of the rectified image M1 against the truth ortho, whole footprint and median
    of 32-pixel tiles (output pixels of 0.5 m)."""
    import numpy as np
    import rasterio
    from swathflow.formats.raster import read_raster
    from shifts import shift_report
    from truth_ortho import overlap_with_truth
    truth = read_raster(mission / "truth" / "ortho.tif", masked_to_nan=True)
    with rasterio.open(rect_dir / "M1.tif") as src:
        rect = src.read(1).astype(float)
        if src.nodata is not None:
            rect[rect == src.nodata] = np.nan
        sub_r, sub_t = overlap_with_truth(rect, src.transform, truth)
    assert np.isfinite(sub_r).mean() > 0.5          # a slanted strip in a north-up box
    rep = shift_report(sub_r, sub_t, tile=32, margin=8)
    return rep["whole_px"], rep["median_tile_px"]


def test_rotating_mirror_mission_validates_and_rectifies_onto_the_truth(mirror_site,
                                                                       mirror_mission,
                                                                       tmp_path):
    """The simulated mission validates, and rectified with the true calibration (the
    mission's own, noisy POS) it lands on the truth ortho. Measured on seeds 1-3: whole
    footprint 0.009-0.030 px, median 32-px tile 0.049-0.054 px (the same with the
    noise-free POS: the floor is image noise and resampling of a 390 x 160 image); a model
    that ignored the plugin's scan_start column would be off by 0.63 px (bias 0.06 deg)."""
    out = tmp_path / "rect"
    r, codes = _cli(mirror_site, ["validate", str(mirror_mission)],
                    ["rectify", str(mirror_mission), "--calibration",
                     str(mirror_mission / "truth" / "calibration.json"), "--out", str(out)])
    assert codes == [0, 0], r.stdout + r.stderr
    assert "OK" in r.stdout and "rotating-mirror" in r.stdout
    whole, median = _mirror_vs_truth(out, mirror_mission)
    assert whole < 0.1 and median < 0.1, (whole, median)


def test_rotating_mirror_scan_start_column_matters(mirror_site, mirror_mission, tmp_path):
    """The comparison can fail: the same mission with every row's scan_start replaced by
    the nominal start angle (what a model ignoring the column assumes) is off the truth."""
    import shutil
    import pandas as pd
    bad = tmp_path / "nominal"
    shutil.copytree(mirror_mission, bad)
    p = bad / "images" / "M1.lines.csv"
    lt = pd.read_csv(p)
    lt["scan_start"] = -(160 - 1) / 2 * 0.1
    lt.to_csv(p, index=False, float_format="%.9f")
    out = tmp_path / "rect"
    r = _run(mirror_site, MIRROR_CLI.format(args=[
        "rectify", str(bad), "--calibration",
        str(mirror_mission / "truth" / "calibration.json"), "--out", str(out)]))
    assert r.returncode == 0, r.stdout + r.stderr
    whole, median = _mirror_vs_truth(out, mirror_mission)
    assert whole > 0.4 and median > 0.3, (whole, median)


def test_rotating_mirror_line_table_checked_by_the_plugin(mirror_site, mirror_mission,
                                                         tmp_path):
    """A non-physical value in the plugin's own column (scan_start beyond 80 deg) is refused
    by `swathflow validate` with the plugin's message (exit 2), as is a missing column."""
    import shutil
    import pandas as pd
    bad = tmp_path / "bad"
    shutil.copytree(mirror_mission, bad)
    p = bad / "images" / "M1.lines.csv"
    lt = pd.read_csv(p)
    lt.loc[7, "scan_start"] = 123.0
    lt.to_csv(p, index=False, float_format="%.9f")
    nocol = tmp_path / "nocol"
    shutil.copytree(mirror_mission, nocol)
    lt.drop(columns="scan_start").to_csv(nocol / "images" / "M1.lines.csv", index=False,
                                         float_format="%.9f")
    r, codes = _cli(mirror_site, ["validate", str(bad)], ["validate", str(nocol)])
    assert codes == [2, 2], r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    first, second = r.stdout.split(str(nocol), 1)
    assert "M1.lines.csv" in first and "column scan_start, file row(s) 9" in first
    assert "beyond +-80 deg from nadir" in first
    assert "missing column(s) scan_start" in second
