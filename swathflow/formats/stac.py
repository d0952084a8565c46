"""A STAC catalogue of a run's products (pystac): a root catalogue (``catalog.json``) holding
one collection (the mission), with one item per rectified swing and one for the mosaic.

Each item's ``datetime`` is its acquisition time (the middle of its lines' times, GPS seconds
of week placed on the mission's ``[mission] date``; see :mod:`swathflow.formats.gpstime`),
with ``start_datetime``/``end_datetime``; without a date, the processing time. Each item
carries the projection extension v1.2.0 (``proj:code``, and ``proj:epsg`` beside it where the
CRS has an EPSG code; shape, transform, native bbox): v1.2.0 is the one version that defines
both fields, v2.0.0's schema forbids ``proj:epsg``, which stackstac 0.5 still needs to pick a
CRS; the raster extension on its
data asset (per band: nodata, data type, resolution), the eo extension with the file's band
names (and centre wavelength and FWHM where known), the file extension (size and sha256
multihash of every local asset) and the processing extension v1.0.0 (software, level,
lineage; the processing time is the core ``created`` field); the calibration, its report
and the mosaic's quicklook (role ``thumbnail``) are assets. The collection declares
``item_assets`` and summaries. Ids are lower case (``[a-z0-9_-]``); the image id as given is
the item's ``swathflow:image_id``.
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
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence

import numpy as np

#: v1.0.0: the version whose JSON schema the tests hold offline (tests/data/stac-schemas);
#: it has no processing:datetime, so the processing time is the core ``created`` field
PROCESSING_SCHEMA = "https://stac-extensions.github.io/processing/v1.0.0/schema.json"
FILE_SCHEMA = "https://stac-extensions.github.io/file/v2.1.0/schema.json"
#: v1.2.0, not v2.0.0: it defines ``proj:code`` and the deprecated ``proj:epsg`` side by side
#: (stackstac 0.5 reads only ``proj:epsg``; v2.0.0's schema forbids it). pystac reads the
#: items as v2.0.0 (its migration keeps ``proj:code``, drops ``proj:epsg``)
PROJECTION_SCHEMA = "https://stac-extensions.github.io/projection/v1.2.0/schema.json"
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
    """The projection facts of the open raster ``src``, as run caches record them."""
    epsg = src.crs.to_epsg()
    out = {"code": f"EPSG:{epsg}"} if epsg else {"wkt2": src.crs.to_wkt()}
    out.update(shape=[src.height, src.width], transform=[float(v) for v in
                                                        list(src.transform)[:6]],
               bbox=[float(v) for v in src.bounds])
    return out


def _proj_fields(proj: Mapping) -> dict:
    """The item properties of the projection extension v1.2.0 for the facts ``proj``:
    ``proj:epsg`` beside ``proj:code`` when the code is an EPSG one."""
    fields = {f"proj:{k}": v for k, v in proj.items()}
    code = str(proj.get("code", ""))
    if code.upper().startswith("EPSG:") and code[5:].isdigit():
        fields["proj:epsg"] = int(code[5:])
    return fields


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


def _micrometres(value: str, units: str) -> float:
    return float(value) / 1000.0 if units.lower().startswith("nan") else float(value)


def _wavelengths(src, given) -> list | None:
    """Band centre wavelengths (micrometres): given, else band tags ``wavelength``."""
    if given is not None:
        return [float(w) for w in given]
    found = []
    for b in range(1, src.count + 1):
        tags = {k.lower(): v for k, v in src.tags(b).items()}
        if "wavelength" not in tags:
            return None
        found.append(_micrometres(tags["wavelength"], tags.get("wavelength_units", "um")))
    return found


def _eo_bands(src) -> list[dict]:
    """Per band: its name (the file's band description, else ``b<i>``) and, from the band
    tags, its full width at half maximum in micrometres where known."""
    out = []
    for b in range(1, src.count + 1):
        tags = {k.lower(): v for k, v in src.tags(b).items()}
        band = {"name": (src.descriptions[b - 1] or f"b{b}")}
        if "fwhm" in tags:
            band["full_width_half_max"] = _micrometres(tags["fwhm"],
                                                       tags.get("wavelength_units", "um"))
        out.append(band)
    return out


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
                "eo_bands": _eo_bands(src),
                "tags": {k: v for k, v in src.tags().items()
                         if k in ("image_id", "strip", "direction", "mission", "sensor")}}


def item_id(image_id: str) -> str:
    """The STAC id of a product named ``image_id``: lower case, ``[a-z0-9_-]`` (what
    catalogue linters ask for); the name as given stays in ``swathflow:image_id``."""
    return re.sub(r"[^a-z0-9_-]+", "-", image_id.lower()).strip("-") or "item"


def _iso(when: dt.datetime) -> str:
    return when.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


def _file_fields(path: str) -> dict:
    """The file extension's size and checksum (sha256 as a multihash) of a local file."""
    from swathflow.cache import file_digest
    return {"file:size": os.path.getsize(path), "file:checksum": "1220" + file_digest(path)}


def _asset(path: str, media: str, roles: list[str], title: str):
    import pystac
    return pystac.Asset(os.path.abspath(path), media_type=media, roles=roles, title=title,
                        extra_fields=_file_fields(path))


def _item(path: str, name: str, span, when: dt.datetime, level: str, lineage: str,
          wavelengths=None, properties: Mapping | None = None, facts: Mapping | None = None):
    """The item of the COG ``path`` named ``name``: acquired over ``span`` (start, end: UTC
    datetimes) or, without one, at ``when``."""
    import pystac
    from pystac.extensions.eo import Band, EOExtension
    from pystac.extensions.raster import RasterBand, RasterExtension
    from swathflow._version import __version__
    facts = facts or raster_facts(path)
    geom, res, proj = facts["geometry"], facts["resolution"], dict(facts["proj"])
    bands = [RasterBand(dict(b)) for b in facts["bands"]]
    waves = [float(w) for w in wavelengths] if wavelengths is not None else facts["wavelengths"]
    count = facts["count"]
    props = {"processing:software": {"swathflow": __version__}, "processing:level": level,
             "processing:lineage": lineage, "created": _iso(dt.datetime.now(dt.UTC)),
             "swathflow:footprint_resolution": res}
    props.update({f"swathflow:{k}": v for k, v in facts["tags"].items()})
    props["swathflow:image_id"] = name
    props.update(properties or {})
    if span is not None:
        start, end = span
        when = start + (end - start) / 2
        props.update(start_datetime=_iso(start), end_datetime=_iso(end))
    item = pystac.Item(item_id(name), geom, _bbox(geom), when, props)
    item.stac_extensions += [PROJECTION_SCHEMA, PROCESSING_SCHEMA, FILE_SCHEMA]
    item.properties.update(_proj_fields(proj))
    asset = _asset(path, COG, ["data"], os.path.basename(path))
    item.add_asset("data", asset)
    RasterExtension.ext(asset, add_if_missing=True).apply(bands)
    named = facts.get("eo_bands") or [{"name": f"b{i + 1}"} for i in range(count)]
    eo = [Band.create(name=b["name"], full_width_half_max=b.get("full_width_half_max"),
                      center_wavelength=(waves[i] if waves is not None and len(waves) == count
                                         else None))
          for i, b in enumerate(named)]
    EOExtension.ext(asset, add_if_missing=True).apply(bands=eo)
    return item


def _side_assets(item, assets: Mapping[str, tuple[str, str, str, list[str]]]) -> None:
    for key, (path, media, title, roles) in assets.items():
        if path and os.path.exists(path):
            item.add_asset(key, _asset(os.fspath(path), media, roles, title))


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


def _collection(collection_id: str, title: str, items: list):
    """The mission's collection: its extents from the items, ``item_assets`` describing
    the items' data asset, and summaries of their bands, CRS codes and resolutions."""
    import pystac
    from pystac.extensions.projection import ProjectionExtension  # noqa: F401 (fields)
    from shapely.geometry import shape
    import shapely
    whole = shapely.union_all([shape(i.geometry) for i in items if i.geometry])
    starts = [i.common_metadata.start_datetime or i.datetime for i in items]
    ends = [i.common_metadata.end_datetime or i.datetime for i in items]
    extent = pystac.Extent(pystac.SpatialExtent([[float(v) for v in whole.bounds]]),
                           pystac.TemporalExtent([[min(starts), max(ends)]]))
    col = pystac.Collection(collection_id, f"Products of {title}: rectified swings and "
                            "mosaic", extent, title=title, license="other")
    data = [i.assets["data"] for i in items]
    names = sorted({b["name"] for a in data for b in a.extra_fields.get("eo:bands", [])})
    col.summaries.add("proj:code", sorted({i.properties["proj:code"] for i in items
                                           if "proj:code" in i.properties}))
    col.summaries.add("eo:bands", [{"name": n} for n in names])
    col.summaries.add("processing:level", sorted({i.properties["processing:level"]
                                                  for i in items}))
    col.item_assets = {"data": pystac.ItemAssetDefinition.create(
        title="the product (COG)", description="orthorectified swing or mosaic",
        media_type=COG, roles=["data"])}
    col.stac_extensions += [PROCESSING_SCHEMA, FILE_SCHEMA]
    return col


def write_catalog(rectified: Sequence, mosaic=None, out="stac", *, calibration=None,
                  report=None, mosaic_report=None, quicklook=None, title: str = "swathflow run",
                  catalog_id: str = "swathflow", acquired: dt.datetime | None = None,
                  spans: Mapping | None = None, wavelengths: Mapping | None = None,
                  facts: Mapping | None = None) -> str:
    """Write a self-contained STAC catalogue of a run's products into the folder ``out``
    and return the path of its ``catalog.json``: the root catalogue, holding the
    collection ``catalog_id`` with the items.

    ``rectified``: the per-swing COGs (named by their file stem); ``mosaic``: the mosaic
    COG (item ``mosaic``); ``calibration``, ``report``: assets of every item;
    ``mosaic_report`` (JSON or HTML) and ``quicklook`` (PNG, the thumbnail): assets of the
    mosaic item. ``spans``: name -> (start, end) acquisition times (UTC datetimes) of the
    swings; the mosaic spans them all. Items without a span are dated ``acquired``,
    default the processing time. ``wavelengths``: name -> band centre wavelengths in
    micrometres (default: band tags ``wavelength``). ``facts``: name -> :func:`raster_facts`
    of that product, already known (the flow's rectify task records them); the others are
    read from the files.
    """
    import pystac
    when = acquired or dt.datetime.now(dt.UTC)
    spans = dict(spans or {})
    out = os.path.abspath(os.fspath(out))
    if "#" in out or "?" in out:    # pystac reads them as a URL's fragment or query: the
        from swathflow.errors import SwathflowError     # files would land elsewhere
        raise SwathflowError(f"{out}: a STAC catalogue cannot be written to a path with "
                             f"'#' or '?' (read as part of a URL): choose another folder")
    cal_assets = {"calibration": (calibration, "application/json", "calibration parameters",
                                  ["metadata"]),
                  "report": (report, "text/html", "calibration report", ["metadata"])}
    wavelengths = wavelengths or {}
    facts = facts or {}
    items, names = [], {}
    for path in rectified:
        name = os.path.splitext(os.path.basename(os.fspath(path)))[0]
        item = _item(os.fspath(path), name, spans.get(name), when, "orthorectified swing",
                     "one swing orthorectified onto the terrain with the per-direction "
                     "calibration", wavelengths.get(name), facts=facts.get(name))
        _side_assets(item, cal_assets)
        items.append(item)
    if mosaic is not None:
        known = [spans[n] for n in (os.path.splitext(os.path.basename(os.fspath(p)))[0]
                                    for p in rectified) if n in spans]
        span = (min(s for s, _ in known), max(e for _, e in known)) if known else None
        item = _item(os.fspath(mosaic), "mosaic", span, when, "mosaic",
                     f"{len(rectified)} rectified swings strip-matched and blended",
                     wavelengths.get("mosaic"), {"swathflow:swings": len(rectified)},
                     facts=facts.get("mosaic"))
        _side_assets(item, {**cal_assets,
                            "mosaic-report": (mosaic_report, _media(mosaic_report),
                                              "mosaic report", ["metadata"]),
                            "thumbnail": (quicklook, "image/png", "quicklook",
                                          ["thumbnail", "overview"])})
        items.append(item)
    for item in items:
        if item.id in names:
            raise ValueError(f"products {names[item.id]!r} and "
                             f"{item.properties['swathflow:image_id']!r} have the same STAC "
                             f"id {item.id!r}: rename one of the images")
        names[item.id] = item.properties["swathflow:image_id"]
    catalog = pystac.Catalog(item_id(catalog_id), f"Products of {title}", title=title)
    if items:
        collection = _collection(item_id(catalog_id) + "-products", title, items)
        collection.add_items(items)
        catalog.add_child(collection)
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
