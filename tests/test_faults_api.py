"""Issue 44, the Python API: an argument out of range or of the wrong type is a
:class:`~swathflow.errors.SwathflowError` (also a ValueError or TypeError) naming the
argument and what it accepts, raised before any work, never an obscure error from inside
(dask's chunking, ``range()``, an attribute lookup)."""
from __future__ import annotations

import numpy as np
import pytest
import swathflow
from swathflow.errors import ArgumentError, ArgumentTypeError, FormatError


@pytest.mark.parametrize("tile, error, words", [
    (-1, ArgumentError, ("tile=-1", "1 or more")),
    (0, ArgumentError, ("tile=0", "1 or more")),
    (8, ArgumentError, ("tile=8", "from 16 to 4096")),
    (100000000, ArgumentError, ("tile=100000000", "from 16 to 4096")),
    (100, ArgumentError, ("tile=100", "multiple of 16")),
    ("512", ArgumentTypeError, ("tile='512'", "whole number")),
    (512.0, ArgumentTypeError, ("tile=512.0", "whole number")),
])
def test_rectify_tile_out_of_range(tiny_mission, tile, error, words):
    """``rectify(..., tile=-1)`` was dask's "Empty tuples are not allowed in chunks"."""
    with pytest.raises(error) as e:
        swathflow.rectify(tiny_mission, "L1", tile=tile)
    assert all(w in str(e.value) for w in words), e.value


def test_geolocation_and_mosaic_tile_out_of_range(tiny_mission):
    with pytest.raises(ArgumentError, match="tile=0"):
        swathflow.geolocation(tiny_mission, "L1", product="glt", tile=0)
    with pytest.raises(ArgumentError, match="tile=-16"):
        swathflow.mosaic(["a.tif", "b.tif"], tile=-16)


def test_tile_errors_are_value_and_type_errors():
    assert issubclass(ArgumentError, ValueError)
    assert issubclass(ArgumentTypeError, TypeError)
    assert issubclass(ArgumentError, swathflow.SwathflowError)
    assert issubclass(ArgumentTypeError, swathflow.SwathflowError)


@pytest.mark.parametrize("data", [np.zeros((4, 4), np.float32), [[1.0, 2.0]], None])
def test_to_cog_of_something_not_a_dataarray(tmp_path, data):
    """``to_cog(numpy_array)`` was "'numpy.ndarray' object has no attribute 'dims'"."""
    with pytest.raises(ArgumentTypeError) as e:
        swathflow.to_cog(data, tmp_path / "x.tif")
    assert "xarray.DataArray" in str(e.value) and "da must be" in str(e.value)
    assert not list(tmp_path.iterdir())


def test_to_cog_blocksize_out_of_range(tmp_path):
    import xarray as xr
    da = xr.DataArray(np.zeros((32, 32), np.float32), dims=("y", "x"))
    with pytest.raises(ArgumentError, match="blocksize=-1"):
        swathflow.to_cog(da, tmp_path / "x.tif", blocksize=-1)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("fmt", [5, 1.5, ["sbet"]])
def test_read_pos_format_not_a_name(tiny_mission, fmt):
    with pytest.raises(FormatError) as e:
        swathflow.read_pos(tiny_mission / "pos.sbet", format=fmt)
    assert "pos.sbet" in str(e.value) and "sbet" in str(e.value).split("got")[0]
