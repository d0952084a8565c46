"""The run's STAC catalogue: pystac's validator (core schemas shipped in pystac, offline),
every declared extension validated against its JSON schema held offline
(tests/data/stac-schemas, see tests/stac_schemas.py), pystac's extension classes reading
back the fields, and footprints against the known valid-data polygon of synthetic COGs."""
import datetime as dt
import json
import socket
from pathlib import Path

import numpy as np
import pystac
import pytest
import rasterio
from pyproj import Transformer
from pystac.extensions.eo import EOExtension
from pystac.extensions.projection import ProjectionExtension
from pystac.extensions.raster import RasterExtension
from pystac.validation import validate_dict
from rasterio.transform import from_origin
from shapely.geometry import Polygon, shape
from stac_schemas import validate_extensions
from swathflow.formats.stac import PROCESSING_SCHEMA, write_catalog

CRS = "EPSG:32633"
X0, Y0, GSD = 500000.0, 5300000.0, 0.5


@pytest.fixture
def offline(monkeypatch):
    """No network: any connection attempt fails the test (the schemas must be local)."""
    def refuse(*a, **k):
        raise AssertionError("network access attempted")
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def _rotated(cx, cy, length, width, angle_deg):
    """Corners (col, row) of a rotated rectangle: the valid data of a swing."""
    a = np.radians(angle_deg)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    c = np.array([cx, cy])
    return [c + su * length / 2 * u + sv * width / 2 * v
            for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]


def _write_swing(path, corners, shape_=(400, 600), dtype="uint16", nodata=0, tags=None,
                 band_tags=None):
    rows, cols = np.mgrid[0:shape_[0], 0:shape_[1]] + 0.5
    inside = Polygon(corners)
    from shapely import contains_xy
    mask = contains_xy(inside, cols, rows)
    data = np.where(mask, 1000 + (rows + cols).astype(int) % 500, nodata).astype(dtype)
    profile = {"driver": "COG", "width": shape_[1], "height": shape_[0], "count": 1,
               "dtype": dtype, "crs": CRS, "transform": from_origin(X0, Y0, GSD, GSD),
               "nodata": nodata}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
        dst.update_tags(**(tags or {}))
        if band_tags:
            dst.update_tags(1, **band_tags)
    return mask


def _truth_lonlat(corners):
    to = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    xy = [(X0 + c * GSD, Y0 - r * GSD) for c, r in corners]
    return Polygon([to.transform(x, y) for x, y in xy])


def _iou(a, b):
    return a.intersection(b).area / a.union(b).area


def test_catalogue_validates_and_describes_the_products(tmp_path, offline):
    run = tmp_path / "run"
    (run / "rectified").mkdir(parents=True)
    (run / "calibration").mkdir()
    corners = {"L1": _rotated(300, 200, 520, 140, 25), "R1": _rotated(300, 200, 560, 120, -35)}
    for iid, c in corners.items():
        _write_swing(run / "rectified" / f"{iid}.tif", c,
                     tags={"image_id": iid, "direction": iid[0], "strip": "1"},
                     band_tags={"wavelength": "10.5"} if iid == "L1" else None)
    mosaic_corners = [(10, 10), (590, 10), (590, 390), (300, 100), (10, 390)]  # concave
    _write_swing(run / "mosaic.tif", mosaic_corners, dtype="float32", nodata=-9999.0)
    (run / "calibration" / "calibration.json").write_text("{}")
    (run / "calibration" / "report.html").write_text("<html></html>")
    (run / "mosaic.json").write_text("{}")
    path = write_catalog([run / "rectified" / "L1.tif", run / "rectified" / "R1.tif"],
                         run / "mosaic.tif", run / "stac",
                         calibration=run / "calibration" / "calibration.json",
                         report=run / "calibration" / "report.html",
                         mosaic_report=run / "mosaic.json", title="test run")
    assert Path(path) == run / "stac" / "catalog.json"
    assert not [p for p in run.iterdir() if p.name.startswith(".")]   # no temporary left
    cat = pystac.Catalog.from_file(path)
    # ids in lower case (catalogue linters ask for it), the image id as given beside
    items = {i.properties["swathflow:image_id"]: i for i in cat.get_items(recursive=True)}
    assert set(items) == {"L1", "R1", "mosaic"}
    assert {i.id for i in items.values()} == {"l1", "r1", "mosaic"}
    for item in items.values():
        d = json.loads(Path(item.self_href).read_text())
        validate_dict(d, extensions=[])          # STAC core item schema, shipped in pystac
        used = validate_extensions(d)           # extension schemas, held offline
        assert {u.split("/")[3] for u in used} >= {"projection", "raster", "processing"}
        assert {u.split("/")[3] for u in used} >= {"eo", "file"}
        assert PROCESSING_SCHEMA in d["stac_extensions"]
        assert d["properties"]["processing:software"]["swathflow"]
        assert d["properties"]["processing:level"]
        # projection: what rasterio reads from the file
        with rasterio.open(item.assets["data"].get_absolute_href()) as src:
            proj = ProjectionExtension.ext(item)
            assert proj.code == CRS
            assert proj.shape == [src.height, src.width]
            assert proj.transform == pytest.approx(list(src.transform)[:6])
            band = RasterExtension.ext(item.assets["data"]).bands[0]
            assert str(getattr(band.data_type, "value", band.data_type)) == src.dtypes[0]
            assert band.nodata == src.nodata
            assert band.spatial_resolution == pytest.approx(GSD)
        assert item.assets["calibration"].get_absolute_href() == str(
            run / "calibration" / "calibration.json")
        assert item.assets["report"].media_type == "text/html"
        assert not Path(item.assets["data"].href).is_absolute()   # self-contained
    validate_dict(json.loads(Path(path).read_text()), extensions=[])
    # wavelengths where known (L1 has a band tag), none invented for R1
    assert EOExtension.ext(items["L1"].assets["data"]).bands[0].center_wavelength == 10.5
    assert [b.center_wavelength for b in EOExtension.ext(items["R1"].assets["data"]).bands] \
        == [None]
    assert items["mosaic"].assets["mosaic-report"].get_absolute_href() == str(run / "mosaic.json")
    # footprints are the valid data, not the bounding box
    for iid, c in {**corners, "mosaic": mosaic_corners}.items():
        foot = shape(items[iid].geometry)
        truth = _truth_lonlat(c)
        assert _iou(foot, truth) > 0.97, iid
        box = Polygon.from_bounds(*foot.bounds)
        assert foot.area < 0.8 * box.area, iid
        assert items[iid].bbox == pytest.approx(list(foot.bounds))
        assert foot.exterior.is_ccw, iid                      # RFC 7946 winding
        assert len(foot.exterior.coords) < 40, (iid, len(foot.exterior.coords))  # simplified


def test_rewrite_replaces_the_catalogue_whole(tmp_path, offline):
    (tmp_path / "rectified").mkdir()
    c = _rotated(300, 200, 400, 100, 10)
    for iid in ("A", "B"):
        _write_swing(tmp_path / "rectified" / f"{iid}.tif", c)
    write_catalog([tmp_path / "rectified" / "A.tif", tmp_path / "rectified" / "B.tif"],
                  None, tmp_path / "stac")
    path = write_catalog([tmp_path / "rectified" / "A.tif"], None, tmp_path / "stac")
    ids = {i.id for i in pystac.Catalog.from_file(path).get_items(recursive=True)}
    assert ids == {"a"}
    assert not list((tmp_path / "stac").rglob("b.json"))


@pytest.mark.parametrize("where, key, bad", [
    ("properties", "proj:code", 32633),                        # must be a string
    ("properties", "proj:shape", [400]),                       # two integers
    ("properties", "processing:level", 2),                     # a string
    ("properties", "processing:datetime", "2026-01-01T00:00:00Z"),   # not in v1.0.0
    ("raster", "data_type", "uint17"),                         # not a raster data type
    ("eo", "center_wavelength", "10.5"),                       # a number
])
def test_extension_schemas_reject_wrong_fields(tmp_path, offline, where, key, bad):
    """The offline extension schemas catch a wrong field of each extension (so the check
    above can fail)."""
    import jsonschema
    (tmp_path / "r").mkdir()
    _write_swing(tmp_path / "r" / "L1.tif", _rotated(300, 200, 400, 100, 10),
                 band_tags={"wavelength": "10.5"})
    path = write_catalog([tmp_path / "r" / "L1.tif"], None, tmp_path / "stac")
    item = next(pystac.Catalog.from_file(path).get_items(recursive=True))
    d = json.loads(Path(item.self_href).read_text())
    validate_extensions(d)
    if where == "properties":
        d["properties"][key] = bad
    else:
        d["assets"]["data"][f"{where}:bands"][0][key] = bad
    with pytest.raises(jsonschema.ValidationError):
        validate_extensions(d)


def test_facts_recorded_with_a_swing_describe_it_until_it_changes(tmp_path, offline):
    """The flow's rectify task records each swing's catalogue facts (footprint traced as
    the swing is written) in its stage manifest; the catalogue uses them, with the truth
    footprint, only while the file is the one they describe."""
    from swathflow.cache import mark_done
    from swathflow.tasks.swings import catalog_facts, recorded_facts
    (tmp_path / "r").mkdir()
    corners = _rotated(300, 200, 520, 140, 25)
    path = tmp_path / "r" / "L1.tif"
    _write_swing(path, corners, tags={"image_id": "L1"})
    mark_done(path, "key", **catalog_facts(path))
    facts = recorded_facts(path)
    assert facts is not None
    when = dt.datetime(2026, 5, 1, tzinfo=dt.UTC)
    cat = write_catalog([path], None, tmp_path / "stac", facts={"L1": facts}, acquired=when)
    item = next(pystac.Catalog.from_file(cat).get_items(recursive=True))
    validate_dict(item.to_dict(), extensions=[])
    validate_extensions(item.to_dict())
    assert _iou(shape(item.geometry), _truth_lonlat(corners)) > 0.98
    assert item.properties["swathflow:image_id"] == "L1"
    again = write_catalog([path], None, tmp_path / "stac2", acquired=when)   # from the file
    read = next(pystac.Catalog.from_file(again).get_items(recursive=True)).to_dict()
    given = item.to_dict()
    for d in (read, given):
        d["properties"].pop("created")
        d.pop("links")
    assert read == given
    _write_swing(path, _rotated(300, 200, 400, 100, -10))     # the swing rewritten
    assert recorded_facts(path) is None


# ---- the ecosystem's conventions (issue 46) --------------------------------------------
GPS_WEEK_2317 = dt.datetime(2024, 6, 2, tzinfo=dt.UTC)      # GPS week 2317 began on Sunday


def _swings_with_times(tmp_path, n=3):
    """``n`` synthetic swings over one scene (different DN so that slices differ) and
    their acquisition spans, one minute apart."""
    (tmp_path / "r").mkdir(exist_ok=True)
    paths, spans = [], {}
    for k in range(n):
        p = tmp_path / "r" / f"S{k}.tif"
        _write_swing(p, _rotated(300, 200, 520, 140, 10 * k),
                     tags={"image_id": f"S{k}"})
        with rasterio.open(p, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
            dst.set_band_description(1, "red")
            dst.update_tags(1, fwhm="0.05", wavelength="0.66")
        start = dt.datetime(2024, 6, 5, 12, k, tzinfo=dt.UTC)
        spans[f"S{k}"] = (start, start + dt.timedelta(seconds=20))
        paths.append(p)
    return paths, spans


def test_items_carry_acquisition_times_bands_files_and_a_collection(tmp_path, offline):
    import hashlib
    paths, spans = _swings_with_times(tmp_path)
    (tmp_path / "m.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    cat = write_catalog(paths, paths[0], tmp_path / "stac", spans=spans,
                        quicklook=tmp_path / "m.png", catalog_id="Sim Mission")
    root = pystac.Catalog.from_file(cat)
    (col,) = list(root.get_children())
    assert isinstance(col, pystac.Collection) and col.id == "sim-mission-products"
    items = {i.properties["swathflow:image_id"]: i for i in col.get_items()}
    for name, (start, end) in spans.items():
        item = items[name]
        assert item.common_metadata.start_datetime == start
        assert item.common_metadata.end_datetime == end
        assert item.datetime == start + (end - start) / 2
        eo = EOExtension.ext(item.assets["data"]).bands
        assert [(b.name, b.center_wavelength, b.full_width_half_max) for b in eo] == \
            [("red", 0.66, 0.05)]
        data = item.assets["data"]
        raw = Path(data.get_absolute_href()).read_bytes()
        assert data.extra_fields["file:size"] == len(raw)
        assert data.extra_fields["file:checksum"] == "1220" + hashlib.sha256(raw).hexdigest()
        assert item.properties["proj:code"] == CRS
    mos = items["mosaic"]
    assert mos.common_metadata.start_datetime == min(s for s, _ in spans.values())
    assert mos.common_metadata.end_datetime == max(e for _, e in spans.values())
    assert "thumbnail" in mos.assets["thumbnail"].roles
    assert col.extent.temporal.intervals == [[min(s for s, _ in spans.values()),
                                             max(e for _, e in spans.values())]]
    assert col.item_assets["data"].media_type.startswith("image/tiff")
    assert col.summaries.get_list("proj:code") == [CRS]
    assert col.summaries.get_list("eo:bands") == [{"name": "red"}]
    assert not [p.name for p in (tmp_path / "stac").rglob("*") if "swathflow" in p.name]


def test_odc_stac_and_stackstac_load_the_pixels_of_the_cogs(tmp_path, offline):
    """The real clients, no extra arguments: odc-stac keeps one time slice per swing
    (groupby time), and both give the files' pixels on the files' grid."""
    import odc.stac
    import stackstac
    paths, spans = _swings_with_times(tmp_path)
    cat = write_catalog(paths, None, tmp_path / "stac", spans=spans)
    items = list(pystac.Catalog.from_file(cat).get_items(recursive=True))
    truth = {}
    for p in paths:
        with rasterio.open(p) as src:
            truth[p.stem.lower()] = src.read(1)
    ds = odc.stac.load(items, groupby="time")
    assert ds.sizes["time"] == len(paths)
    order = sorted(items, key=lambda i: i.datetime)
    for k, item in enumerate(order):
        got = ds["data"].isel(time=k).values
        assert got.shape == truth[item.id].shape
        assert np.array_equal(got, truth[item.id])
    # stackstac, no extra arguments, on the items as written (JSON): it picks the CRS from
    # proj:epsg, which the items carry beside proj:code (pystac's reader migrates the items
    # to projection v2.0.0 and drops proj:epsg, so its items need epsg=: stackstac#262)
    docs = []
    for item in items:
        d = json.loads(Path(item.self_href).read_text())
        assert d["properties"]["proj:epsg"] == int(CRS.split(":")[1])
        assert d["properties"]["proj:code"] == CRS
        # stackstac opens the hrefs as they are: resolve the catalogue's relative ones
        d["assets"]["data"]["href"] = item.assets["data"].get_absolute_href()
        docs.append(d)
    arr = stackstac.stack(docs).compute()
    assert arr.sizes["time"] == len(paths)
    assert arr.attrs["crs"].upper() == CRS
    for k, iid in enumerate(arr["id"].values):
        got = arr.isel(time=k, band=0).values
        want = truth[str(iid)]
        assert got.shape == want.shape
        # stackstac fills nodata with NaN (float64 by default): the valid pixels are equal
        valid = want != 0
        assert np.array_equal(got[valid], want[valid].astype(got.dtype))
        assert np.isnan(got[~valid]).all()


class _LocalSchemas(pystac.stac_io.DefaultStacIO):
    """pystac's reader with the extension schemas held in tests/data/stac-schemas."""

    def read_text(self, source, *args, **kwargs):
        from stac_schemas import SCHEMAS
        href = str(source)
        if href.startswith("https://stac-extensions.github.io/"):
            return (SCHEMAS / href.removeprefix("https://")).read_text(encoding="utf-8")
        return super().read_text(source, *args, **kwargs)


def test_catalogue_validates_offline_with_pystac_and_stac_validator(tmp_path, offline):
    from stac_schemas import validator_schema_map
    from stac_validator.stac_validator import StacValidate
    paths, spans = _swings_with_times(tmp_path)
    cat = write_catalog(paths, paths[0], tmp_path / "stac", spans=spans)
    pystac.StacIO.set_default(_LocalSchemas)
    try:
        root = pystac.Catalog.from_file(cat)
        assert root.validate_all() == len(paths) + 1          # items validated
    finally:
        pystac.StacIO.set_default(pystac.stac_io.DefaultStacIO)
    schema_map = validator_schema_map()
    docs = sorted((tmp_path / "stac").rglob("*.json"))
    assert len(docs) == 1 + 1 + len(paths) + 1          # catalogue, collection, items
    for doc in docs:
        v = StacValidate(str(doc), schema_map=schema_map)
        assert v.run(), (doc, v.message)
    # and it can fail: a field the projection schema does not define
    bad = json.loads(docs[-1].read_text())
    bad["properties"]["proj:epsgcode"] = 32633
    docs[-1].write_text(json.dumps(bad))
    v = StacValidate(str(docs[-1]), schema_map=schema_map)
    assert not v.run() and "proj:epsgcode" in v.message[0]["error_message"]


@pytest.mark.parametrize("seconds, day, expected", [
    (302400.0, dt.date(2024, 6, 5), dt.datetime(2024, 6, 5, 11, 59, 42, tzinfo=dt.UTC)),
    (0.0, dt.date(2024, 6, 2), GPS_WEEK_2317 - dt.timedelta(seconds=18)),
    (86400.0 * 6 + 3600, dt.date(2016, 12, 31),                    # before the 2017 leap
     dt.datetime(2016, 12, 31, 0, 59, 43, tzinfo=dt.UTC)),
])
def test_gps_seconds_of_week_on_the_flight_date(seconds, day, expected):
    from swathflow.formats.gpstime import gps_seconds_of_week_to_utc, week_start
    assert week_start(dt.date(2024, 6, 5)) == dt.datetime(1980, 1, 6, tzinfo=dt.UTC) \
        + dt.timedelta(weeks=2317)
    assert gps_seconds_of_week_to_utc(seconds, day) == expected


def test_a_flight_date_that_does_not_hold_the_pos_is_refused():
    from swathflow.formats.gpstime import date_mismatch
    assert date_mismatch(302400.0, dt.date(2024, 6, 5)) is None
    assert "Wednesday" in date_mismatch(302400.0, dt.date(2024, 6, 4))
    assert "GPS second of week" in date_mismatch(-5.0, dt.date(2024, 6, 5))
