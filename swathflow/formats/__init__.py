"""File formats: POS trajectories (readers are plugins: formats.navigation), the run's STAC
catalogue, rasters (GeoTIFF/COG, ENVI), calibration files. Readers check what they read and
raise FormatError with the file and the fix."""
