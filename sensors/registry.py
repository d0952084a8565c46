"""The sensor registry: built-in and third-party models through one entry-point group.

Built-ins register through ``swathflow.sensors`` like any plugin and are also known
statically, so an editable install never loses them. A plugin that fails to load, is not a
:class:`SensorModel`, or clashes with a registered name warns and is skipped.
"""
from __future__ import annotations

import warnings
from functools import lru_cache
from importlib.metadata import entry_points

from swathflow.errors import SwathflowError

from swathflow.sensors.base import SensorModel

GROUP = "swathflow.sensors"
BUILTINS = {
    "pendulum": "swathflow.sensors.pendulum:PendulumModel",
    "pushbroom": "swathflow.sensors.pushbroom:PushbroomModel",
}


class SensorPluginWarning(UserWarning):
    """A sensor plugin could not be registered."""


def _load(target: str):
    from importlib import import_module
    module, _, attr = target.partition(":")
    obj = import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@lru_cache(maxsize=1)
def _registry() -> dict[str, tuple[type[SensorModel], str]]:
    found: dict[str, tuple[type[SensorModel], str]] = {}
    for name, target in BUILTINS.items():
        found[name] = (_load(target), target)
    for ep in entry_points(group=GROUP):
        if ep.name in found:
            if found[ep.name][1] != ep.value:
                warnings.warn(SensorPluginWarning(
                    f"sensor plugin {ep.name!r} from {ep.value} clashes with "
                    f"{found[ep.name][1]}; skipped"), stacklevel=3)
            continue
        cls = _load_plugin(ep)
        if cls is not None:
            found[ep.name] = (cls, ep.value)
    return found


def _load_plugin(ep):
    """The plugin's class, or None after a warning: a broken plugin never breaks the host,
    whatever it raises at import (SystemExit and KeyboardInterrupt included)."""
    try:
        cls = ep.load()
    except BaseException as exc:
        if isinstance(exc, KeyboardInterrupt):   # the user's Ctrl-C
            raise
        warnings.warn(SensorPluginWarning(
            f"sensor plugin {ep.name!r} ({ep.value}) failed to load: "
            f"{type(exc).__name__}: {exc}; skipped"), stacklevel=4)
        return None
    if not (isinstance(cls, type) and issubclass(cls, SensorModel)):
        warnings.warn(SensorPluginWarning(
            f"sensor plugin {ep.name!r} ({ep.value}) is not a SensorModel subclass; "
            f"skipped"), stacklevel=4)
        return None
    missing = sorted(getattr(cls, "__abstractmethods__", ()) or ())
    if missing:
        warnings.warn(SensorPluginWarning(
            f"sensor plugin {ep.name!r} ({ep.value}) is incomplete: the SensorModel "
            f"subclass does not implement {', '.join(missing)}; skipped"), stacklevel=4)
        return None
    return cls


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
