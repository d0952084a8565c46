"""The sensor registry: built-in and third-party models through one entry-point group.

The built-in models (:mod:`swathflow.sensors`) register through ``swathflow.sensors`` like
any plugin, and are registered first: a third-party plugin that clashes with one of their
names warns and is skipped, as does one that fails to load or is not a
:class:`SensorModel` (the discovery is :func:`swathflow.entrypoints.discover`, shared with
the navigation formats).
"""
from __future__ import annotations

from functools import lru_cache
from importlib.metadata import entry_points

from swathflow.entrypoints import discover
from swathflow.errors import SwathflowError, SwathflowWarning

from swathflow.sensormodel.base import SensorModel

GROUP = "swathflow.sensors"


class SensorPluginWarning(SwathflowWarning):
    """A sensor plugin could not be registered."""


def _problem(cls) -> str | None:
    """What keeps ``cls`` from being a sensor model, or None."""
    if not (isinstance(cls, type) and issubclass(cls, SensorModel)):
        return "is not a SensorModel subclass"
    missing = sorted(getattr(cls, "__abstractmethods__", ()) or ())
    if missing:
        return f"is incomplete: the SensorModel subclass does not implement {', '.join(missing)}"
    return None


@lru_cache(maxsize=1)
def _registry() -> dict[str, tuple[type[SensorModel], str]]:
    points = sorted(entry_points(group=GROUP), key=lambda ep: not _built_in(ep))
    return discover({}, points, _problem, SensorPluginWarning, "sensor")


def _built_in(ep) -> bool:
    """Whether the entry point is one of swathflow's own (they are registered first)."""
    dist = getattr(ep, "dist", None)
    return dist is not None and dist.name == "swathflow"


def list_sensors() -> dict[str, type[SensorModel]]:
    """Registered sensor models by name (built-ins first)."""
    return {k: v[0] for k, v in _registry().items()}


def get_sensor(name: str) -> type[SensorModel]:
    """The sensor-model class registered under ``name``."""
    reg = _registry()
    if name not in reg:
        raise SwathflowError(f"unknown sensor model {name!r}; registered: "
                             f"{', '.join(sorted(reg)) or 'none'} (see 'swathflow sensors')")
    return reg[name][0]


def refresh() -> None:
    """Forget the cached discovery (after installing a plugin in a running process)."""
    _registry.cache_clear()
