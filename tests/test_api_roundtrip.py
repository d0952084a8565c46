"""The Python API takes what it gives and its objects round-trip: rectify and mosaic take
the open_mission tree (with its ``pos`` node edited), the arrays and the tree write with
``to_netcdf`` and ``to_zarr`` and read back equal, a swing's graph pickles with plain
pickle, the arrays plot with a plain title and a labelled colour bar, and the API
docstrings' examples run as doctests."""
import doctest
import json
import pickle

import numpy as np
import pytest
import rasterio
import xarray as xr

import swathflow
from swathflow.errors import SwathflowError
from test_api import _against_truth


@pytest.fixture(scope="module")
def cal(tiny_mission):
    return tiny_mission / "truth" / "calibration.json"


def test_rectify_and_mosaic_take_the_open_mission_tree(tiny_mission, cal):
    tree = swathflow.open_mission(tiny_mission)
    from_tree = swathflow.rectify(tree, "L1", cal)
    _against_truth(from_tree, tiny_mission)
    from swathflow.ingest.mission import load_mission
    from_mission = swathflow.rectify(load_mission(tiny_mission), "L1", cal)
    assert np.array_equal(from_tree.values, from_mission.values, equal_nan=True)
    mos = swathflow.mosaic(tree, calibration=cal, tile=128)
    assert json.loads(mos.attrs["report"])["inputs"] == len(tree["images"].children) == 2
    _against_truth(mos, tiny_mission)


def test_an_edited_pos_node_moves_the_image_by_the_edit(tiny_mission, cal):
    """The aircraft moved 3 m east in the tree's ``pos`` node: the rectified image sits
    3 m east of the truth (the terrain is a DEM, so allow a little relief parallax)."""
    tree = swathflow.open_mission(tiny_mission)
    pos = tree["pos"].to_dataset()
    east = 3.0
    dlon = np.degrees(east / (6378137.0 * np.cos(np.radians(float(pos["lat"].mean())))))
    tree["pos"] = pos.assign(lon=pos["lon"] + dlon)
    moved = swathflow.rectify(tree, "L1", cal)
    from shifts import phase_shift
    with rasterio.open(tiny_mission / "truth" / "ortho.tif") as t:
        truth = t.read(1, masked=True).astype(float).filled(np.nan)
        tt = t.transform
    tr = moved.rio.transform()
    col0, row0 = round((tr.c - tt.c) / tt.a), round((tr.f - tt.f) / tt.e)
    img = np.asarray(moved.values, float)
    win = truth[row0:row0 + img.shape[0], col0:col0 + img.shape[1]]
    ok = np.isfinite(img) & np.isfinite(win)
    dy, dx = phase_shift(np.where(ok, img, np.nanmean(img[ok])),
                         np.where(ok, win, np.nanmean(win[ok])))
    assert abs(dx * tt.a - east) < 0.25 * east and abs(dy * tt.a) < 0.1 * east, (dx, dy)
    # the tree's trajectory is what the mission is then made of; the unedited tree is not
    from swathflow.ingest.api import as_mission
    assert np.allclose(as_mission(tree).pos["lon"], pos["lon"] + dlon)
    assert as_mission(swathflow.open_mission(tiny_mission)).pos.identical(pos)


def test_what_is_not_a_mission_is_a_clear_error(tiny_mission):
    with pytest.raises(SwathflowError, match="DataTree of swathflow.open_mission"):
        swathflow.rectify(42, "L1")
    with pytest.raises(SwathflowError, match="no 'path' attribute"):
        swathflow.rectify(xr.DataTree(), "L1")


def _same(a: xr.DataArray, b: xr.DataArray):
    """Values, coordinates and attributes equal; ``_FillValue`` may move to the encoding
    on reading (xarray's CF decoding)."""
    assert np.array_equal(np.asarray(a.values), np.asarray(b.values), equal_nan=True)
    strip = {"_FillValue"}
    assert {k: v for k, v in a.attrs.items() if k not in strip} == \
        {k: v for k, v in b.attrs.items() if k not in strip}
    for name, c in a.coords.items():
        assert np.array_equal(np.asarray(c.values), np.asarray(b.coords[name].values)), name
        assert c.attrs == b.coords[name].attrs, name


@pytest.mark.parametrize("store", ["netcdf", "zarr"])
def test_rectified_and_mosaic_arrays_round_trip(tiny_mission, cal, tmp_path, store):
    swings = [swathflow.rectify(tiny_mission, i, cal, tile=128) for i in ("L1", "R1")]
    mos = swathflow.mosaic(swings, tile=128)
    for arr in swings + [mos]:
        path = tmp_path / f"{arr.name}.{store}"
        if store == "netcdf":
            arr.to_netcdf(path, engine="scipy")             # netCDF-3: the strictest
            back = xr.open_dataarray(path, engine="scipy", decode_coords="all")
        else:
            arr.to_dataset().to_zarr(path)
            back = xr.open_zarr(path, decode_coords="all")[arr.name]
        with back:
            _same(arr, back)
            assert back.rio.crs == arr.rio.crs and back.rio.transform() == arr.rio.transform()
    assert json.loads(back.attrs["report"])["inputs"] == 2


@pytest.mark.parametrize("store", ["netcdf", "zarr"])
def test_the_open_mission_tree_round_trips(tiny_mission, tmp_path, store):
    tree = swathflow.open_mission(tiny_mission)
    path = tmp_path / f"tree.{store}"
    if store == "netcdf":
        tree.to_netcdf(path, engine="h5netcdf")
        back = xr.open_datatree(path, engine="h5netcdf", decode_coords="all")
    else:
        tree.to_zarr(path)
        back = xr.open_datatree(path, engine="zarr", decode_coords="all")
    assert back.attrs == tree.attrs
    for node in ("pos", "images/L1", "images/R1"):
        a, b = tree[node].to_dataset(), back[node].to_dataset()
        assert a.attrs == b.attrs
        for name in a.variables:
            _same(a[name], b[name])
    # what was written is a mission again: rectified from the tree read back
    again = swathflow.rectify(back, "L1", tiny_mission / "truth" / "calibration.json")
    _against_truth(again, tiny_mission)


def test_a_swing_graph_pickles(tiny_mission, cal):
    """Plain pickle (what a distributed scheduler falls back to) takes the graph; the
    array unpickled computes the same pixels, on the truth."""
    arr = swathflow.rectify(tiny_mission, "L1", cal, tile=128)
    graph = dict(arr.data.__dask_graph__())
    assert pickle.loads(pickle.dumps(graph)).keys() == graph.keys()
    back = pickle.loads(pickle.dumps(arr))
    _against_truth(back, tiny_mission)
    assert np.array_equal(back.values, arr.values, equal_nan=True)
    glt = swathflow.geolocation(tiny_mission, "L1", cal, "glt", tile=128)
    assert np.array_equal(pickle.loads(pickle.dumps(glt)).values, glt.values)


def test_arrays_plot_with_names_and_units(tiny_mission, cal):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    arr = swathflow.rectify(tiny_mission, "L1", cal, tile=128)
    assert arr.attrs["long_name"] == "digital number" and arr.attrs["units"] == "1"
    assert arr["x"].attrs["standard_name"] == "projection_x_coordinate"
    assert arr["y"].attrs["standard_name"] == "projection_y_coordinate"
    assert arr["x"].attrs["units"] == arr["y"].attrs["units"] == "metre"
    tree = swathflow.open_mission(tiny_mission)
    assert tree["images/L1"]["time"].attrs["units"] == "s"
    fig, ax = plt.subplots()
    try:
        mesh = arr.plot(ax=ax)
        title = ax.get_title()
        assert "description" not in title and "band = 1" in title, title
        assert mesh.colorbar.ax.get_ylabel() == "digital number [1]"
        assert ax.get_xlabel().replace("\n", " ") == "x coordinate of projection [metre]"
    finally:
        plt.close(fig)


def test_api_docstring_examples_run(tiny_mission, tmp_path, monkeypatch):
    """The doctests of the API modules, on the tiny mission (what ``pytest
    --doctest-modules`` runs, with the mission folder given)."""
    import swathflow.ingest.api
    import swathflow.mosaicking.api
    import swathflow.rectification.api
    monkeypatch.chdir(tmp_path)
    for module in (swathflow.ingest.api, swathflow.rectification.api,
                   swathflow.mosaicking.api):
        result = doctest.testmod(module, extraglobs={"swathflow": swathflow,
                                                     "mission_folder": str(tiny_mission)},
                                 optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
        assert result.attempted >= 3 and result.failed == 0, (module.__name__, result)
