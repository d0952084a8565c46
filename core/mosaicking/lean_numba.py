"""numba's start without the parts the mosaic's kernels do not use: the metadata scan for
numba extensions when none is installed, and PyYAML's import when there is no numba
config file to read (:func:`swathflow.mosaicking.mosaic.load_kernels`)."""
from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
import sys
import types

__all__ = ["numba_extensions_declared", "config_without_yaml"]

#: the file numba's config reads from the working folder (numba.core.config)
NUMBA_CONFIG_FILE = ".numba_config.yaml"


def numba_extensions_declared() -> bool:
    """Whether an installed distribution may declare numba extensions (entry point group
    ``numba_extensions``): its ``entry_points.txt`` names the group, or a ``sys.path``
    entry is not a folder to look in. numba's first compilation loads them through
    ``importlib.metadata.entry_points()``, which parses every distribution's entry points
    (178 in this venv: 6.5-11 ms CPU with the collector off, as :func:`load_kernels` runs
    it, on the critical path of a mosaic's start); when none declares any,
    :func:`load_kernels` marks them loaded instead (these reads: 2.5-3.6 ms)."""
    for entry in sys.path:
        folder = entry or "."
        if os.path.isfile(folder):
            return True             # a zip: let numba look
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        for n in names:
            if n.endswith((".dist-info", ".egg-info")):
                try:
                    with open(os.path.join(folder, n, "entry_points.txt"), "rb") as f:
                        if b"numba_extensions" in f.read():
                            return True
                except OSError:
                    pass
    return False


class _YamlOnUse(types.ModuleType):
    """Stands for the ``yaml`` module while numba is imported: the real one is imported
    on the first attribute asked of it (by numba's config, or by another thread that
    imported ``yaml`` meanwhile)."""

    def __getattr__(self, name):
        if sys.modules.get("yaml") is self:
            sys.modules.pop("yaml", None)
        return getattr(importlib.import_module("yaml"), name)


@contextlib.contextmanager
def config_without_yaml():
    """numba's config imports PyYAML (9.5-15 ms CPU with the collector off, on the mosaic's
    critical path)
    only to read :data:`NUMBA_CONFIG_FILE` from the working folder when there is one.
    Without that file, and with neither numba nor yaml loaded yet (and yaml installed),
    numba is imported inside this block with a stand-in for ``yaml`` that imports it on
    first use (numba reads its config again at every compilation: a config file made
    later is still read); after the block ``import yaml`` gives the real module."""
    block = ("numba" not in sys.modules and "yaml" not in sys.modules
             and not os.path.isfile(NUMBA_CONFIG_FILE)
             and importlib.util.find_spec("yaml") is not None)
    standin = _YamlOnUse("yaml")
    if block:
        sys.modules["yaml"] = standin
    try:
        yield
    finally:
        if block and sys.modules.get("yaml") is standin:
            sys.modules.pop("yaml", None)
