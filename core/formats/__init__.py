"""File formats: POS trajectories (SBET, CSV), rasters (GeoTIFF/COG, ENVI), calibration
files. Readers check what they read and raise FormatError with the file and the fix."""
