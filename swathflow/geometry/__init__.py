"""Geometry: rotations, frames and geodesy (pyproj), line solving, terrain and ray
intersection, output grids. Pure numpy; depends only on errors/io."""
