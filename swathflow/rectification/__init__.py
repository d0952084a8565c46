"""Stage 4, rectification: direct georeferencing onto a DEM or a height, resampling,
gap filling, Cloud-Optimized GeoTIFF output.

The engine: the adaptive lattice of exact raw coordinates (:mod:`.lattice`), the compiled
pixel kernels (:mod:`.kernel`), the tile-by-tile dask graph (:mod:`.tiles`) and
multi-band raw-image reading (:mod:`.rawimage`)."""
