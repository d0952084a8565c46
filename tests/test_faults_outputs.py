"""Issue 44, data loss: no output of any command lands on or inside an input of the mission
(every file it or the command reads, wherever it lives), nor outside the output folder it
names. Each case runs the real command line on a copy of a simulated ``tiny`` mission and
checks that the input is byte for byte what it was."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from faultkit import run, toml


def _snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _swing(path: Path, image_id: str, mission: str = "sim-tiny", value: float = 1.0) -> None:
    """A small rectified swing (tagged as the rectify command tags its products)."""
    from swathflow.formats.raster import write_geotiff
    a = np.full((8, 8), value, np.float32)
    write_geotiff(path, a, "EPSG:32651", (0.4, 0, 500000, 0, -0.4, 3000000), nodata=np.nan,
                  tags={"image_id": image_id, "mission": mission, "strip": "1"})


# ------------------------------------------------------------------------------------------
# --out on or over an input, per command

@pytest.mark.parametrize("cmd", ["rectify", "calibrate", "run"])
def test_out_folder_holding_the_raw_images_is_refused(m, capsys, cmd):
    """``rectify M --out M/images`` wrote the products over the raw images (exit 0)."""
    before = _snapshot(m)
    extra = (["--calibration", m / "truth" / "calibration.json"]
             if cmd in ("rectify", "run") else [])
    code, text = run(capsys, cmd, m, "--out", m / "images", *extra)
    assert code == 2 and "input" in text and "images" in text, text
    assert _snapshot(m) == before


def test_calibrate_out_holding_the_prior_calibration_file_is_refused(m, capsys):
    """``[calibration] file = "prior/calibration.json"`` and ``calibrate M --out M/prior``
    overwrote the prior calibration with the result."""
    (m / "prior").mkdir()
    shutil.copy(m / "truth" / "calibration.json", m / "prior" / "calibration.json")
    toml(m, "[calibration]\n", '[calibration]\nfile = "prior/calibration.json"\n')
    before = (m / "prior" / "calibration.json").read_bytes()
    code, text = run(capsys, "calibrate", m, "--out", m / "prior")
    assert code == 2 and "calibration.json" in text, text
    assert (m / "prior" / "calibration.json").read_bytes() == before


def test_rectify_out_where_it_writes_its_calibration_is_refused(m, tmp_path, capsys):
    """rectify writes ``rectify.json`` into its output folder: a calibration file of that
    name there would be replaced by the rectification's summary."""
    cal_dir = tmp_path / "cal"
    cal_dir.mkdir()
    shutil.copy(m / "truth" / "calibration.json", cal_dir / "rectify.json")
    before = (cal_dir / "rectify.json").read_bytes()
    code, text = run(capsys, "rectify", m, "--calibration", cal_dir / "rectify.json",
                      "--out", cal_dir)
    assert code == 2 and "rectify.json" in text, text
    assert (cal_dir / "rectify.json").read_bytes() == before


def test_rectify_into_the_calibrate_output_folder_keeps_the_calibration(m, tmp_path,
                                                                         capsys):
    """``calibrate M --out O`` then ``rectify M --calibration O/calibration.json --out O``:
    the calibration is read, never written over, so the folder is allowed."""
    cal_dir = tmp_path / "cal"
    cal_dir.mkdir()
    shutil.copy(m / "truth" / "calibration.json", cal_dir / "calibration.json")
    before = (cal_dir / "calibration.json").read_bytes()
    code, text = run(capsys, "rectify", m, "--calibration", cal_dir / "calibration.json",
                      "--out", cal_dir, "--images", "L1")
    assert code == 0, text
    assert (cal_dir / "calibration.json").read_bytes() == before
    assert (cal_dir / "L1.tif").exists()


@pytest.mark.parametrize("target", ["dem.tif", "images/L1.tif"])
def test_mosaic_out_on_a_mission_file_is_refused(m, capsys, target):
    """``mosaic M --out M/dem.tif`` replaced the mission's DEM (or a raw image)."""
    (m / "rectified").mkdir()
    _swing(m / "rectified" / "L1.tif", "L1")
    _swing(m / "rectified" / "R1.tif", "R1")
    before = _snapshot(m)
    code, text = run(capsys, "mosaic", m, "--out", m / target, "--workers", "1")
    assert code == 2 and "input" in text, text
    assert _snapshot(m) == before


def test_mosaic_with_mission_out_on_its_gcp_sidecar_is_refused(m, tmp_path, capsys):
    """A mosaic's sidecars count too: ``--out M/gcp.tif`` writes ``M/gcp.json`` and
    ``M/gcp.png``; a mission whose GCP file is ``gcp.json`` would lose it."""
    d = tmp_path / "swings"
    d.mkdir()
    _swing(d / "L1.tif", "L1")
    _swing(d / "R1.tif", "R1")
    shutil.copy(m / "gcp.csv", m / "gcp.png")           # a file the toml names
    toml(m, 'file = "gcp.csv"', 'file = "gcp.csv"\nphoto = "gcp.png"')
    before = _snapshot(m)
    code, text = run(capsys, "mosaic", d, "--mission", m, "--out", m / "gcp.tif",
                      "--workers", "1")
    assert code == 2 and "gcp.png" in text, text
    assert _snapshot(m) == before


# ------------------------------------------------------------------------------------------
# ids are names

@pytest.mark.parametrize("bad", ["../dem", "sub/L1", "mosaic", "..", "L 1", "R1.glt"])
def test_image_id_must_be_a_plain_name(m, capsys, bad):
    """``id = "../dem"`` made rectify overwrite ``M/dem.tif``; an image called ``mosaic``
    clobbered the mosaic's STAC item."""
    toml(m, 'id = "L1"', f'id = "{bad}"')
    code, text = run(capsys, "validate", m)
    assert code == 2 and "id=" in text, text
    assert any(w in text for w in ("plain name", "own products", "another image")), text


def test_rectify_refuses_a_path_as_image_id(m, tmp_path, capsys):
    toml(m, 'id = "L1"', 'id = "../dem"')
    before = _snapshot(m)
    code, text = run(capsys, "rectify", m, "--out", tmp_path / "o" / "r",
                      "--calibration", m / "truth" / "calibration.json")
    assert code == 2 and "../dem" in text, text
    assert _snapshot(m) == before
    assert not (tmp_path / "o" / "dem.tif").exists()


# ------------------------------------------------------------------------------------------
# the STAC writer and '#'

def test_run_out_with_a_hash_never_touches_another_file(m, tmp_path, capsys):
    """``run M --out "/x/victim.txt#2"`` overwrote /x/victim.txt with the STAC catalogue
    (the writer read '#' as a URL fragment) and exited 0."""
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    code, text = run(capsys, "run", m, "--out", f"{victim}#2",
                      "--calibration", m / "truth" / "calibration.json")
    assert code == 2 and "#" in text, text
    assert victim.read_text() == "keep me"


def test_write_catalog_refuses_a_hash_in_its_folder(tmp_path):
    from swathflow.errors import SwathflowError
    from swathflow.formats.stac import write_catalog
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    _swing(tmp_path / "L1.tif", "L1")
    with pytest.raises(SwathflowError, match="#"):
        write_catalog([tmp_path / "L1.tif"], None, f"{victim}#2")
    assert victim.read_text() == "keep me"


# ------------------------------------------------------------------------------------------
# mosaic inputs: earlier mosaics and other missions' swings

def test_mosaic_leaves_an_earlier_mosaic_in_the_folder_out(tmp_path, capsys):
    """``mosaic DIR --out DIR/m2.tif`` blended the earlier mosaic DIR/mosaic.tif as one
    more swing: a swing of value 1 and a mosaic of value 50 gave values above 1."""
    import rasterio
    d = tmp_path / "r"
    d.mkdir()
    _swing(d / "L1.tif", "L1", value=1.0)
    code, text = run(capsys, "mosaic", d, "--out", d / "mosaic.tif", "--workers", "1",
                      "--no-match")
    assert code == 0, text
    with rasterio.open(d / "mosaic.tif", "r+", IGNORE_COG_LAYOUT_BREAK="YES") as ds:
        ds.write(np.full((1, ds.height, ds.width), 50.0, np.float32))
    code, text = run(capsys, "mosaic", d, "--out", d / "m2.tif", "--workers", "1",
                      "--no-match")
    assert code == 0, text
    with rasterio.open(d / "m2.tif") as src:
        a = src.read(1)
    assert np.nanmax(a) == pytest.approx(1.0)


def test_mosaic_refuses_swings_of_two_missions(tmp_path, capsys):
    d = tmp_path / "r"
    d.mkdir()
    _swing(d / "L1.tif", "L1", mission="north")
    _swing(d / "R1.tif", "R1", mission="south")
    code, text = run(capsys, "mosaic", d, "--out", tmp_path / "m.tif", "--workers", "1")
    assert code == 2 and "north" in text and "south" in text, text
    assert not (tmp_path / "m.tif").exists()


def test_run_into_another_missions_products_is_refused(m, tmp_path, capsys):
    """A run into an --out holding another mission's swings kept them; a later mosaic of
    the folder blended both missions."""
    out = tmp_path / "o"
    (out / "rectified").mkdir(parents=True)
    _swing(out / "rectified" / "X7.tif", "X7", mission="another")
    code, text = run(capsys, "run", m, "--out", out,
                      "--calibration", m / "truth" / "calibration.json")
    assert code == 2 and "another" in text, text


def test_simulate_into_the_folder_of_its_own_dem_is_refused(m, capsys):
    """``simulate M --dem M/dem.tif --force`` would write the simulated DEM over the one
    it reads."""
    before = (m / "dem.tif").read_bytes()
    code, text = run(capsys, "simulate", m, "--dem", m / "dem.tif", "--force",
                      "--geometry-only")
    assert code == 2 and "dem.tif" in text, text
    assert (m / "dem.tif").read_bytes() == before
