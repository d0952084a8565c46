"""Stage 4, rectification: direct georeferencing onto a DEM or a height, resampling,
gap filling, Cloud-Optimized GeoTIFF output."""
