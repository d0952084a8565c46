"""Prefect tasks: thin wrappers over the maths in :mod:`swathflow`, passing paths and small
metadata. Heavy arrays stay inside a task (Dask over xarray) and go to disk."""
