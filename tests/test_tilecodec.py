"""The COG tiles compressed here by ISA-L (swathflow.rectification.tilecodec) hold, once
inflated, exactly the bytes GDAL's GTiff driver compresses for the same tile: the padding
of edge tiles and the predictor (2 for integers, 3 for floats) as libtiff applies them.
Checked against tiles GDAL writes itself, for every output type; and a COG written without
the codec (GDAL compressing) reads back the same pixels and overviews."""
from __future__ import annotations

import io
import zlib

import numpy as np
import pytest
import rasterio
from rasterio.io import MemoryFile
from swathflow.rectification import tilecodec, writing
from swathflow.rectification.tifflayout import read_first_ifd
from swathflow.rectification.tilecodec import TileSink, can_encode, encode

BS = 64


def _gdal_tiles(block, predictor: int) -> list[bytes]:
    """The compressed bytes of each tile of ``block`` as GDAL writes them (DEFLATE)."""
    with MemoryFile() as mem:
        with mem.open(driver="GTiff", width=block.shape[1], height=block.shape[0], count=1,
                      dtype=block.dtype.name, tiled=True, blockxsize=BS, blockysize=BS,
                      compress="deflate", predictor=predictor) as dst:
            dst.write(block[None])
        f = io.BytesIO(mem.read())
    ifd = read_first_ifd(f)
    out = []
    for off, n in zip(ifd.offsets.tolist(), ifd.counts.tolist()):
        f.seek(off)
        out.append(f.read(n))
    return out


def _pattern(shape, dtype):
    """A smooth pattern with some noise, (rows, cols) or (bands, rows, cols)."""
    b, r, c = np.ogrid[0:(shape[0] if len(shape) == 3 else 1), 0:shape[-2], 0:shape[-1]]
    v = 1000 + 900 * np.sin(r / 5.0 + b) * np.cos(c / 3.0) + (r * c) % 17
    v = v if len(shape) == 3 else v[0]
    dt = np.dtype(dtype)
    if dt.kind == "i":
        v = v - 1500                    # negative values too
    if dt.kind == "f":
        v = v / 7.0
    return v.astype(dt)


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int16", "uint32", "int32", "float32",
                                   "float64"])
@pytest.mark.parametrize("shape", [(BS, BS), (37, 50)])        # whole, and an edge tile
def test_a_tile_inflates_to_what_gdal_compresses(dtype, shape):
    block = _pattern(shape, dtype)
    predictor = 3 if np.dtype(dtype).kind == "f" else 2
    assert can_encode({"compress": "deflate", "predictor": predictor}, dtype)
    (theirs,) = _gdal_tiles(block, predictor)
    ours = encode(block, BS, predictor)
    assert zlib.decompress(ours) == zlib.decompress(theirs)
    (plain,) = _gdal_tiles(block, 1)
    assert zlib.decompress(encode(block, BS, 1)) == zlib.decompress(plain)


def test_what_the_codec_takes():
    assert not can_encode({"compress": "zstd", "predictor": 2}, "uint16")
    assert not can_encode({"compress": "deflate", "predictor": 2}, "float32")
    assert not can_encode({"compress": "deflate", "predictor": 3}, "uint16")
    assert can_encode({"compress": "DEFLATE"}, "float32")


def test_the_sink_takes_windows_on_the_tile_grid_and_leaves_nodata_tiles_out():
    sink = TileSink(io.BytesIO(), 2, 150, 130, BS, 2, nodata=0)
    with pytest.raises(ValueError, match="tile grid"):
        sink.put(0, 10, np.ones((BS, BS), np.uint16))
    with pytest.raises(ValueError, match="tile grid"):
        sink.put(0, 0, np.ones((2, 50, BS), np.uint16))        # cut short inside the grid
    data = _pattern((2, 150, 130), "uint16")
    data[1, :BS, :BS] = 0                                     # a tile of nodata
    sink.put(0, 0, data[:, :128, :])
    sink.put(128, 0, data[:, 128:, :])
    assert sink.counts.size == 2 * 3 * 3
    assert (sink.counts == 0).tolist() == [j == 9 for j in range(18)]
    f = sink.file
    for j, (off, n) in enumerate(zip(sink.offsets.tolist(), sink.counts.tolist())):
        if not n:
            continue
        b, k = divmod(j, 9)
        r, c = divmod(k, 3)
        f.seek(off)
        got = np.frombuffer(zlib.decompress(f.read(n)), "<u2").reshape(BS, BS)
        got = np.cumsum(got, axis=1, dtype=np.uint16)        # undo the predictor
        want = data[b, r * BS:(r + 1) * BS, c * BS:(c + 1) * BS]
        assert np.array_equal(got[:want.shape[0], :want.shape[1]], want)


@pytest.mark.parametrize("dtype,nodata", [("uint16", 0), ("float32", float("nan"))])
def test_a_cog_reads_the_same_with_or_without_the_codec(tmp_path, monkeypatch, dtype, nodata):
    data = _pattern((2, 300, 290), dtype)
    data[:, :, :70] = nodata
    paths = []
    for name, isal in (("isal", tilecodec.isal_zlib), ("gdal", None)):
        monkeypatch.setattr(tilecodec, "isal_zlib", isal)
        path = tmp_path / f"{name}.tif"
        writing.write_cogs([{"path": path, "array": data, "grid": None, "nodata": nodata}],
                           blocksize=BS)
        paths.append(path)
    with rasterio.open(paths[0]) as a, rasterio.open(paths[1]) as b:
        assert a.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        pa, pb = dict(a.profile), dict(b.profile)
        assert repr(pa.pop("nodata")) == repr(pb.pop("nodata")) == repr(float(nodata))
        assert pa == pb and a.overviews(1) == b.overviews(1) == [2, 4, 8]
        assert np.array_equal(a.read(), data, equal_nan=True)
        assert np.array_equal(a.read(), b.read(), equal_nan=True)
        for k in range(len(a.overviews(1))):
            with rasterio.open(paths[0], overview_level=k) as x, \
                    rasterio.open(paths[1], overview_level=k) as y:
                assert np.array_equal(x.read(), y.read(), equal_nan=True)
    assert paths[0].read_bytes() != paths[1].read_bytes()     # the codec was used


def test_tiles_go_to_a_scratch_file_beside_a_part_on_disk(tmp_path, monkeypatch):
    """An output past the in-memory limit: its ``.part`` and its compressed tiles go to
    scratch files beside the target, removed once the COG is laid out; the same pixels and
    overviews as the ``.part`` in memory."""
    data = _pattern((300, 290), "uint16")
    writing.write_cogs([{"path": tmp_path / "mem.tif", "array": data, "grid": None,
                         "nodata": 0}], blocksize=BS)
    made = []
    real = writing.scratch_path

    def watched(target, kind):
        made.append(kind)
        return real(target, kind)
    monkeypatch.setattr(writing, "scratch_path", watched)
    monkeypatch.setattr(writing, "PART_RAM_BYTES", 0)
    writing.write_cogs([{"path": tmp_path / "disk.tif", "array": data, "grid": None,
                         "nodata": 0}], blocksize=BS)
    assert made == ["part.tif", "tiles"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk.tif", "mem.tif"]
    assert (tmp_path / "disk.tif").read_bytes() == (tmp_path / "mem.tif").read_bytes()
    with rasterio.open(tmp_path / "disk.tif") as a:
        assert np.array_equal(a.read(1), data) and a.overviews(1) == [2, 4, 8]
