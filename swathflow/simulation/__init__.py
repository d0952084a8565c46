"""Simulation support shared by the sensor plugins' simulators: textures, terrain,
rendering and writing of mission bundles with their ground truth."""
from __future__ import annotations

from typing import Any, Callable

from swathflow.errors import SwathflowError


def simulators() -> dict[str, Any]:
    """Preset name -> the simulator of the registered sensor plugin that offers it."""
    from swathflow.sensormodel.registry import list_sensors
    found: dict[str, Any] = {}
    for cls in list_sensors().values():
        sim = cls.simulator()
        for preset in getattr(sim, "PRESETS", ()) if sim is not None else ():
            found.setdefault(str(preset), sim)
    return found


def simulate(out, preset: str = "tiny", seed: int = 0,
             progress: Callable[[str], None] | None = None, **options: Any) -> dict:
    """Write a simulated mission bundle with its truth into ``out`` through the simulator of
    the sensor plugin that offers ``preset``; returns the truth summary."""
    sims = simulators()
    if preset not in sims:
        raise SwathflowError(f"unknown preset {preset!r}; choose one of "
                             f"{', '.join(sorted(sims)) or 'none (no simulator registered)'}")
    return sims[preset].simulate(out, preset, seed, progress=progress, **options)
