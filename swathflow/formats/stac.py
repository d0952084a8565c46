"""A STAC catalogue of a run's products (pystac): one item per rectified swing, one for
the mosaic.

Each item carries the projection extension (code, shape, transform, native bbox), the raster
extension on its data asset (per band: nodata, data type, resolution), the eo extension where
wavelengths are known, and the processing extension v1.0.0 (software, level, lineage; the
processing time is the core ``created`` field); the calibration and its report are assets.
Footprints are polygons of the valid data (the nodata mask traced with
``rasterio.features.shapes`` on a decimated mask, simplified to about one decimated pixel,
in EPSG:4326), not bounding boxes. The catalogue folder is written beside the products and
swapped in whole, so readers never see half of it.
"""
from __future__ import annotations

import contextlib
import datetime as dt
import math
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence

import numpy as np

#: v1.0.0: the version whose JSON schema the tests hold offline (tests/data/stac-schemas);
#: it has no processing:datetime, so the processing time is the core ``created`` field
PROCESSING_SCHEMA = "https://stac-extensions.github.io/processing/v1.0.0/schema.json"
COG = "image/tiff; application=geotiff; profile=cloud-optimized"
MAX_MASK = 1024          # footprints are traced on a mask at most this many pixels across


def traced_whole(height: int, width: int, max_size: int = MAX_MASK) -> bool:
    """Whether :func:`valid_footprint` traces a raster of this size at full resolution
    (at most ``max_size`` pixels across), where a writer's kept valid mask is used."""
    return max(height, width) <= max_size


def valid_footprint(src, max_size: int = MAX_MASK, valid=None) -> tuple[dict, float]:
    """The valid-data polygon(s) of an open rasterio dataset as GeoJSON in EPSG:4326, and
    the tracing resolution in the dataset's units. ``valid``: the dataset's mask as its
    writer made it (``to_cog(valid=...)``; what ``dataset_mask`` would read), used instead
    of reading it when the dataset is traced at full resolution (at most ``max_size``
    pixels across)."""
    import shapely
    from affine import Affine
    from rasterio.features import shapes
    from rasterio.warp import transform_geom
    from shapely.geometry import mapping, shape

    f = max(1, math.ceil(max(src.height, src.width) / max_size))
    oh, ow = math.ceil(src.height / f), math.ceil(src.width / f)
    if traced_whole(src.height, src.width, max_size) and valid is not None and \
            valid.shape == (src.height, src.width):
        mask = valid
    else:
        mask = src.dataset_mask(out_shape=(oh, ow))
    tr = src.transform @ Affine.scale(src.width / ow, src.height / oh)
    polys = [shape(g) for g, v in shapes((mask > 0).astype(np.uint8), mask=mask > 0,
                                         transform=tr) if v == 1]
    if not polys:
        return {"type": "Polygon", "coordinates": []}, 0.0
    res = max(abs(tr.a), abs(tr.e))
    geom = shapely.union_all(polys).simplify(2.0 * res, preserve_topology=True)
    geo = shape(transform_geom(src.crs, "EPSG:4326", mapping(geom), precision=9))
    # RFC 7946: exterior rings counter-clockwise, holes clockwise
    return mapping(shapely.orient_polygons(geo, exterior_cw=False)), res


def _bbox(geom: dict) -> list[float]:
    from shapely.geometry import shape
    return [float(v) for v in shape(geom).bounds]


def _proj(src) -> dict:
    epsg = src.crs.to_epsg()
    out = {"code": f"EPSG:{epsg}"} if epsg else {"wkt2": src.crs.to_wkt()}
    out.update(shape=[src.height, src.width], transform=[float(v) for v in
                                                        list(src.transform)[:6]],
               bbox=[float(v) for v in src.bounds])
    return out


def _raster_bands(src) -> list:
    from pystac.extensions.raster import DataType, RasterBand
    res = float(abs(src.transform.a))
    bands = []
    for i in range(src.count):
        nodata = src.nodatavals[i]
        if nodata is not None and isinstance(nodata, float) and math.isnan(nodata):
            nodata = "nan"
        bands.append(RasterBand.create(nodata=nodata, data_type=DataType(src.dtypes[i]),
                                       spatial_resolution=res))
    return bands


def _wavelengths(src, given) -> list | None:
    """Band centre wavelengths (micrometres): given, else band tags ``wavelength``."""
    if given is not None:
        return [float(w) for w in given]
    found = []
    for b in range(1, src.count + 1):
        tags = {k.lower(): v for k, v in src.tags(b).items()}
        if "wavelength" not in tags:
            return None
        w = float(tags["wavelength"])
        units = tags.get("wavelength_units", "micrometers").lower()
        found.append(w / 1000.0 if units.startswith("nan") else w)
    return found


def raster_facts(path, valid=None) -> dict:
    """What a catalogue item says of a COG, read from the file (JSON-ready): its valid-data
    footprint (:func:`valid_footprint`) and tracing resolution, the projection fields, the
    raster bands, the band wavelengths (band tags), the band count and the product tags.
    The flow's rectify task records them with each swing as it is written
    (:func:`swathflow.tasks.swings.rectify_swing`), so the catalogue need not read the
    swings again. ``valid``: the file's valid mask as written (see
    :func:`valid_footprint`)."""
    import rasterio
    with rasterio.open(os.fspath(path)) as src:
        geom, res = valid_footprint(src, valid=valid)
        return {"geometry": geom, "resolution": res, "proj": _proj(src),
                "bands": [b.to_dict() for b in _raster_bands(src)],
                "wavelengths": _wavelengths(src, None), "count": src.count,
                "tags": {k: v for k, v in src.tags().items()
                         if k in ("image_id", "strip", "direction", "mission", "sensor")}}


def _item(path: str, item_id: str, when: dt.datetime, level: str, lineage: str,
          wavelengths=None, properties: Mapping | None = None, facts: Mapping | None = None):
    import pystac
    from pystac.extensions.eo import Band, EOExtension
    from pystac.extensions.projection import ProjectionExtension
    from pystac.extensions.raster import RasterBand, RasterExtension
    from swathflow._version import __version__
    facts = facts or raster_facts(path)
    geom, res, proj = facts["geometry"], facts["resolution"], dict(facts["proj"])
    bands = [RasterBand(dict(b)) for b in facts["bands"]]
    waves = [float(w) for w in wavelengths] if wavelengths is not None else facts["wavelengths"]
    count = facts["count"]
    props = {"processing:software": {"swathflow": __version__}, "processing:level": level,
             "processing:lineage": lineage,
             "created": dt.datetime.now(dt.UTC).isoformat().replace("+00:00", "Z"),
             "swathflow:footprint_resolution": res}
    props.update({f"swathflow:{k}": v for k, v in facts["tags"].items()})
    props.update(properties or {})
    item = pystac.Item(item_id, geom, _bbox(geom), when, props)
    item.stac_extensions.append(PROCESSING_SCHEMA)
    ProjectionExtension.ext(item, add_if_missing=True).apply(**proj)
    asset = pystac.Asset(os.path.abspath(path), media_type=COG, roles=["data"],
                         title=os.path.basename(path))
    item.add_asset("data", asset)
    RasterExtension.ext(asset, add_if_missing=True).apply(bands)
    if waves is not None and len(waves) == count:
        EOExtension.ext(asset, add_if_missing=True).apply(bands=[
            Band.create(name=f"b{i + 1}", center_wavelength=w) for i, w in enumerate(waves)])
    return item


def _side_assets(item, assets: Mapping[str, tuple[str, str, str]]) -> None:
    import pystac
    for key, (path, media, title) in assets.items():
        if path and os.path.exists(path):
            item.add_asset(key, pystac.Asset(os.path.abspath(path), media_type=media,
                                             roles=["metadata"], title=title))


def _swap_in(tmp: str, out: str) -> None:
    """Replace the folder ``out`` by ``tmp`` (rename; the old one removed after)."""
    old = None
    if os.path.exists(out):
        old = tempfile.mkdtemp(prefix=".stac-old-", dir=os.path.dirname(out))
        os.rmdir(old)
        os.replace(out, old)
    os.replace(tmp, out)
    if old:
        shutil.rmtree(old, ignore_errors=True)


def write_catalog(rectified: Sequence, mosaic=None, out="stac", *, calibration=None,
                  report=None, mosaic_report=None, quicklook=None, title: str = "swathflow run",
                  catalog_id: str = "swathflow", acquired: dt.datetime | None = None,
                  wavelengths: Mapping | None = None, facts: Mapping | None = None) -> str:
    """Write a self-contained STAC catalogue of a run's products into the folder ``out``
    and return the path of its ``catalog.json``.

    ``rectified``: the per-swing COGs (item id: the file stem); ``mosaic``: the mosaic COG
    (item ``mosaic``); ``calibration``, ``report``: assets of every item; ``mosaic_report``
    (JSON or HTML) and ``quicklook`` (PNG): assets of the mosaic item. ``acquired``: the
    acquisition time (the mission format has no date: default the processing time).
    ``wavelengths``: item id -> band centre wavelengths in micrometres (default: band tags
    ``wavelength``). ``facts``: item id -> :func:`raster_facts` of that product, already
    known (the flow's rectify task records them); the others are read from the files.
    """
    import pystac
    when = acquired or dt.datetime.now(dt.UTC)
    out = os.path.abspath(os.fspath(out))
    if "#" in out or "?" in out:    # pystac reads them as a URL's fragment or query: the
        from swathflow.errors import SwathflowError     # files would land elsewhere
        raise SwathflowError(f"{out}: a STAC catalogue cannot be written to a path with "
                             f"'#' or '?' (read as part of a URL): choose another folder")
    cal_assets = {"calibration": (calibration, "application/json", "calibration parameters"),
                  "report": (report, "text/html", "calibration report")}
    catalog = pystac.Catalog(catalog_id, f"Products of {title}: rectified swings and mosaic",
                             title=title)
    wavelengths = wavelengths or {}
    facts = facts or {}
    for path in rectified:
        iid = os.path.splitext(os.path.basename(os.fspath(path)))[0]
        item = _item(os.fspath(path), iid, when, "orthorectified swing",
                     "one swing orthorectified onto the terrain with the per-direction "
                     "calibration", wavelengths.get(iid), facts=facts.get(iid))
        _side_assets(item, cal_assets)
        catalog.add_item(item)
    if mosaic is not None:
        item = _item(os.fspath(mosaic), "mosaic", when, "mosaic",
                     f"{len(rectified)} rectified swings strip-matched and blended",
                     wavelengths.get("mosaic"), {"swathflow:swings": len(rectified)},
                     facts=facts.get("mosaic"))
        _side_assets(item, {**cal_assets,
                            "mosaic-report": (mosaic_report, _media(mosaic_report),
                                              "mosaic report"),
                            "overview": (quicklook, "image/png", "quicklook")})
        catalog.add_item(item)
    parent = os.path.dirname(out)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(out)}-", dir=parent)
    try:
        catalog.normalize_hrefs(tmp)
        catalog.make_all_asset_hrefs_relative()
        catalog.save(pystac.CatalogType.SELF_CONTAINED)
        os.chmod(tmp, 0o777 & ~_umask())
        _swap_in(tmp, out)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(tmp)
        raise
    return os.path.join(out, "catalog.json")


def _media(path) -> str:
    return "text/html" if path and str(path).endswith(".html") else "application/json"


def _umask() -> int:
    from swathflow.io import _umask as umask
    return umask()
