"""Raw images for the rectifier: windowed, multi-band, native-dtype reads.

Sources: a numpy array (2-D ``(line, element)`` or 3-D ``(band, line, element)``, memmaps
included), an xarray DataArray / Dataset (data var ``dn``, dims ``line``, ``element`` and
optionally ``band``), a dask array, or a file: ENVI BSQ / BIL / BIP with its ``.hdr``
(memory-mapped, any interleave, either byte order: :mod:`swathflow.formats.envi`) or
anything rasterio reads (multi-band GeoTIFF...). Reads return the native dtype,
``(bands, lines, elements)``; a memory-mapped window's pages are released by
:mod:`.pages`.

Band metadata (names, wavelengths, their units, FWHM) comes from the ENVI header or from
GDAL band descriptions / metadata, and selection works by 1-based index (``"1,4-6"``) or
by wavelength (``"550nm,0.67um"``: the nearest band, within its FWHM or half the band
spacing).
"""
from __future__ import annotations

import math
import os
import re
import threading
from dataclasses import dataclass, field

import numpy as np
from swathflow.errors import FormatError
from swathflow.formats.envi import envi_header_path, map_envi
from swathflow.ingest.images import open_raw

#: a raster file (read through rasterio) of at most this many bytes in its selected bands
#: is read whole, once, and its tiles' windows are views of it (:meth:`RawImage._whole`)
WHOLE_READ_BYTES = 256 << 20
_WHOLE_LOCK = threading.Lock()

_UNITS_NM = {"nm": 1.0, "nanometers": 1.0, "nanometer": 1.0, "um": 1e3, "µm": 1e3,
             "micrometers": 1e3, "micrometer": 1e3, "microns": 1e3, "micron": 1e3,
             "mm": 1e6, "millimeters": 1e6}


@dataclass(frozen=True)
class BandInfo:
    """One band: 1-based ``index`` in the file, ``description``, ``wavelength`` and
    ``fwhm`` (in ``units``, or None) ."""

    index: int
    description: str = ""
    wavelength: float | None = None
    fwhm: float | None = None
    units: str | None = None

    def tags(self) -> dict:
        """The band's GDAL tags in an output COG: its source band, wavelength and FWHM."""
        t = {"source_band": str(self.index)}
        if self.wavelength is not None:
            t["wavelength"] = repr(self.wavelength)
            t["wavelength_units"] = self.units or ""
        if self.fwhm is not None:
            t["fwhm"] = repr(self.fwhm)
        return t


@dataclass(eq=False)
class RawImage:
    """A raw image ``(bands, lines, elements)`` with windowed native-dtype reads.

    ``data`` is an array-like (numpy, memmap, dask) or None with ``path`` a raster file
    read through rasterio. ``selected`` are the 0-based band positions read (all by
    default); ``two_d`` marks a 2-D source whose rectification stays 2-D."""

    data: object
    nodata: float | None = None
    bands: list = field(default_factory=list)
    path: str = ""
    interleave: str = ""
    selected: tuple = ()
    two_d: bool = False

    def __post_init__(self):
        if self.data is not None:
            self.shape3 = tuple(int(n) for n in self.data.shape)
            self.dtype = np.dtype(self.data.dtype).newbyteorder("=")
        if not self.bands:
            self.bands = [BandInfo(i + 1) for i in range(self.shape3[0])]
        if not self.selected:
            self.selected = tuple(range(self.shape3[0]))

    # --- shape ------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """(lines, elements), as the sensor model's shape."""
        return self.shape3[1], self.shape3[2]

    @property
    def count(self) -> int:
        """The number of bands read (selected)."""
        return len(self.selected)

    @property
    def band_info(self) -> list[BandInfo]:
        """The selected bands' metadata, in the order they are read."""
        return [self.bands[i] for i in self.selected]

    def select(self, spec) -> RawImage:
        """A view reading only the bands of ``spec`` (see :func:`parse_bands`)."""
        sel = parse_bands(spec, self.bands, self.path or "raw image")
        return RawImage(self.data, self.nodata, self.bands, self.path, self.interleave,
                        tuple(sel), False) if self.data is not None else \
            _with_rasterio(self, tuple(sel))

    # --- reads ------------------------------------------------------------------------
    def read(self, l0: int, l1: int, e0: int, e1: int) -> np.ndarray:
        """``(bands, l1 - l0, e1 - e0)`` in the native dtype (native byte order). A numpy
        (memory-mapped) source is copied in its own interleave: the result's memory is
        BIL / BIP ordered for a BIL / BIP file (see :func:`_native_window`)."""
        if self.data is None:
            whole = self._whole()
            if whole is not None:
                return whole[:, l0:l1, e0:e1]
            from rasterio.windows import Window
            with open_raw(self.path) as src:
                a = src.read([i + 1 for i in self.selected],
                             window=Window(e0, l0, e1 - e0, l1 - l0))
            return a
        sel = list(self.selected)
        if isinstance(self.data, np.ndarray):
            return _native_window(self.data, sel, l0, l1, e0, e1)
        if sel == list(range(self.shape3[0])):
            a = self.data[:, l0:l1, e0:e1]
        elif len(sel) == 1:
            a = self.data[sel[0]:sel[0] + 1, l0:l1, e0:e1]
        else:
            a = np.stack([self.data[i, l0:l1, e0:e1] for i in sel])
        if hasattr(a, "compute"):
            from dask.local import get_sync      # a function: dask imports no distributed
            a = a.compute(scheduler=get_sync)
        a = np.asarray(getattr(a, "values", a))
        if not a.dtype.isnative:
            a = a.astype(a.dtype.newbyteorder("="))
        return np.ascontiguousarray(a)

    def _whole(self) -> np.ndarray | None:
        """The selected bands of a file read through rasterio, read once and kept (a swing
        of at most :data:`WHOLE_READ_BYTES`): every tile's window is then a view of it,
        instead of one file open and windowed read per tile. None for larger images."""
        n = self.count * self.shape3[1] * self.shape3[2] * self.dtype.itemsize
        if n > WHOLE_READ_BYTES:
            return None
        with _WHOLE_LOCK:
            whole = self.__dict__.get("_whole_cache")
            if whole is None:
                with open_raw(self.path) as src:
                    whole = src.read([i + 1 for i in self.selected])
                whole.setflags(write=False)
                self.__dict__["_whole_cache"] = whole
        return whole

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_whole_cache", None)          # read again where it is used, not sent
        return state

    def token(self):
        """What identifies the image's content for dask (file or array, bands, type)."""
        return (self.path or id(self.data), self.selected, str(self.dtype), self.nodata)


def _native_window(data: np.ndarray, sel: list, l0, l1, e0, e1) -> np.ndarray:
    """A window of a ``(bands, lines, elements)`` numpy view of any axis order (an ENVI
    memmap: BSQ, BIL or BIP) as a ``(bands, lines, elements)`` array in that order.

    Native byte order and a run of consecutive bands: a view, no copy at all (the kernels
    address it through its strides, :func:`.gather.storage_view`). Otherwise a copy in
    the file's own order (no transposing copy), of the selected bands only."""
    if sel == list(range(sel[0], sel[-1] + 1)) and data.dtype.isnative:
        return data[sel[0]:sel[-1] + 1, l0:l1, e0:e1]
    v = data[:, l0:l1, e0:e1]
    order = sorted(range(3), key=lambda a: -v.strides[a])     # storage order of the axes
    st = np.take(v.transpose(order), sel, axis=order.index(0))  # C-ordered, storage order
    if not st.dtype.isnative:
        st = st.astype(st.dtype.newbyteorder("="))
    return st.transpose(np.argsort(order))


def _with_rasterio(img: RawImage, sel) -> RawImage:
    """A file read through rasterio with other bands selected (its cached whole read not
    shared)."""
    out = RawImage.__new__(RawImage)
    out.__dict__.update(img.__getstate__())
    out.selected = sel
    out.two_d = False
    return out


def _open_rasterio(path: str, nodata=None) -> RawImage:
    """Any raster rasterio reads (multi-band GeoTIFF...), its band metadata from the GDAL
    band descriptions and tags; the pixels are read per window (:meth:`RawImage.read`)."""
    import rasterio
    try:
        with open_raw(path) as src:
            shape3 = (src.count, src.height, src.width)
            dtype = np.dtype(src.dtypes[0])
            nd = src.nodata if nodata is None else nodata
            infos = []
            for i in range(1, src.count + 1):
                md = src.tags(i)
                wl = md.get("wavelength")
                fw = md.get("fwhm")
                infos.append(BandInfo(i, src.descriptions[i - 1] or "",
                                      float(wl) if wl not in (None, "") else None,
                                      float(fw) if fw not in (None, "") else None,
                                      md.get("wavelength_units") or None))
    except rasterio.errors.RasterioIOError as exc:
        raise FormatError(f"{path}: cannot read image: {exc}") from None
    img = RawImage.__new__(RawImage)
    img.data, img.nodata, img.bands, img.path = None, nd, infos, path
    img.interleave, img.shape3, img.dtype = "", shape3, dtype
    img.selected, img.two_d = tuple(range(shape3[0])), shape3[0] == 1
    return img


class RawSource:
    """The former single-band reader, kept for its callers: band 1 (the first selected
    band) of any raw image :func:`open_raw_image` accepts, read as float64 ``(lines,
    elements)`` with NaN for nodata. The engine itself reads :attr:`image`."""

    def __init__(self, data, nodata=None):
        self.image = open_raw_image(data, nodata=nodata)
        self.shape = self.image.shape
        self.dtype = self.image.dtype
        self.nodata = self.image.nodata

    def read(self, l0: int, l1: int, e0: int, e1: int) -> np.ndarray:
        """``(l1 - l0, e1 - e0)`` of band 1 as float64, NaN for nodata."""
        a = self.image.read(l0, l1, e0, e1)[0].astype(np.float64)
        nd = self.nodata
        if nd is not None and not (isinstance(nd, float) and math.isnan(nd)):
            a[a == nd] = np.nan
        return a

    def token(self):
        """:meth:`RawImage.token` of the image read."""
        return self.image.token()


def open_raw_image(image, nodata=None, bands=None) -> RawImage:
    """A :class:`RawImage` from a path (ENVI or any raster), an array (2-D or 3-D),
    an xarray object, a :class:`RawImage` or a :class:`RawSource`; ``bands`` selects a
    subset."""
    if isinstance(image, RawSource):
        image = image.image
    if isinstance(image, RawImage):
        img = image
    elif isinstance(image, (str, os.PathLike)):
        path = os.fspath(image)
        if not os.path.exists(path):
            raise FormatError(f"{path}: raw image not found")
        img = _open_envi(path) if envi_header_path(path) else _open_rasterio(path, nodata)
        if nodata is not None:
            img.nodata = nodata
    else:
        img = _from_array(image, nodata)
    return img.select(bands) if bands not in (None, "", ()) else img


def _open_envi(path: str) -> RawImage:
    """An ENVI image (BSQ, BIL or BIP, memory-mapped: :func:`~swathflow.formats.envi.map_envi`)
    with its bands' names, wavelengths and FWHM."""
    e = map_envi(path)
    bands = [BandInfo(i + 1, e.names[i] if i < len(e.names) else "", e.wavelengths[i],
                      e.fwhm[i], e.units if e.wavelengths[i] is not None else None)
             for i in range(e.data.shape[0])]
    return RawImage(e.data, e.nodata, bands, path=e.path, interleave=e.interleave)


def _from_array(data, nodata) -> RawImage:
    """An array source: numpy (memmaps included) or dask, 2-D ``(line, element)`` or 3-D
    ``(band, line, element)``, or an xarray DataArray / Dataset (``dn``) with those dims,
    its wavelengths and nodata (``_FillValue`` or ``nodata``) from its metadata."""
    infos = []
    if hasattr(data, "data_vars"):          # xarray Dataset
        data = data["dn"]
    if hasattr(data, "dims") and hasattr(data, "transpose"):   # xarray DataArray
        dims = ("band", "line", "element") if "band" in data.dims else ("line", "element")
        data = data.transpose(*dims)
        if nodata is None:
            nodata = data.attrs.get("_FillValue", data.attrs.get("nodata"))
        if "wavelength" in data.coords and "band" in data.dims:
            wl = np.asarray(data["wavelength"].values, float)
            units = data["wavelength"].attrs.get("units")
            infos = [BandInfo(i + 1, "", float(w), None, units) for i, w in enumerate(wl)]
        data = data.data
    two_d = data.ndim == 2
    if two_d:
        data = data[None]
    if data.ndim != 3:
        raise FormatError(f"a raw image must be 2-D (line, element) or 3-D (band, line, "
                          f"element), got shape {data.shape}")
    if nodata is not None and isinstance(nodata, float) and math.isnan(nodata):
        nodata = None                           # NaN is always nodata
    return RawImage(data, nodata, infos, two_d=two_d)


# ----------------------------------------------------------------------------------------
# band selection
# ----------------------------------------------------------------------------------------
_WL = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*(nm|um|µm)\s*$", re.IGNORECASE)


def parse_bands(spec, infos: list[BandInfo], where: str = "raw image") -> list[int]:
    """0-based band positions from ``spec``: 1-based indices and ranges (``"1,3,5-8"``),
    wavelengths with a unit (``"550nm"``, ``"0.67um"``: the nearest band, within its
    FWHM, or half the spacing to its neighbours when the header has no FWHM), or a list
    of ints (1-based)."""
    n = len(infos)
    items = spec if isinstance(spec, (list, tuple)) else str(spec).split(",")
    out: list[int] = []
    for it in items:
        tok = str(it).strip()
        if not tok:
            continue
        m = _WL.match(tok)
        if m:
            out.append(_by_wavelength(float(m.group(1)) * _UNITS_NM[m.group(2).lower()
                                                                    .replace("µ", "u")],
                                      tok, infos, where))
            continue
        rng = re.fullmatch(r"(\d+)\s*-\s*(\d+)", tok)
        try:
            lo, hi = (int(rng.group(1)), int(rng.group(2))) if rng else (int(tok), int(tok))
        except ValueError:
            raise FormatError(f"{where}: band {tok!r} is neither a 1-based index, a range "
                              f"(3-7) nor a wavelength with a unit (550nm, 0.55um)") from None
        if not (1 <= lo <= hi <= n):
            raise FormatError(f"{where}: band {tok} is out of range; the image has bands "
                              f"1-{n}")
        out.extend(range(lo - 1, hi))
    if not out:
        raise FormatError(f"{where}: the band selection {spec!r} selects no band")
    return out


def _by_wavelength(nm: float, tok: str, infos, where) -> int:
    wl = np.array([_to_nm(b) for b in infos], float)
    if not np.isfinite(wl).any():
        raise FormatError(f"{where}: band {tok} asks for a wavelength but the image has no "
                          f"band wavelengths (with units); select bands by index instead")
    i = int(np.nanargmin(np.abs(wl - nm)))
    fw = infos[i].fwhm
    if fw is not None and infos[i].units:
        tolerance = fw * _UNITS_NM.get(infos[i].units.lower(), math.nan)
    else:
        others = np.abs(np.delete(wl, i) - wl[i]) if len(wl) > 1 else np.array([np.inf])
        tolerance = np.nanmin(others)
    if not abs(wl[i] - nm) <= max(tolerance / 2 if fw is None else tolerance, 1e-9):
        raise FormatError(f"{where}: no band at {tok}: the nearest is band {i + 1} at "
                          f"{wl[i]:g} nm")
    return i


def _to_nm(b: BandInfo) -> float:
    """A band's wavelength in nanometres (NaN: none, or units unknown)."""
    if b.wavelength is None or not b.units:
        return math.nan
    return b.wavelength * _UNITS_NM.get(b.units.lower(), math.nan)
