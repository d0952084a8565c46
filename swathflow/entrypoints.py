"""Plugin discovery through an entry-point group, the one way for every registry (sensor
models, navigation formats).

Built-ins are known statically and registered first, so an editable install never loses
them; they are also declared in the group like any plugin. A third-party entry point that
clashes with a registered name, fails to load (whatever it raises at import, Ctrl-C aside)
or fails the registry's check warns and is skipped: a broken plugin never breaks the host.
"""
from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable, Mapping
from importlib import import_module


def load_target(target: str):
    """The object named by ``"package.module:attr.path"``."""
    module, _, attr = target.partition(":")
    obj = import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def discover(builtins: Mapping[str, str], found_points: Iterable,
             check: Callable[[object], str | None], warning: type[Warning],
             kind: str) -> dict[str, tuple]:
    """``{name: (object, target)}``: the ``builtins`` (name -> target), then the other
    entry points of ``found_points`` (``importlib.metadata.entry_points(group=...)``, passed
    in by the registry so that tests can replace it). ``check(obj)`` returns None for a
    valid plugin, else what is wrong with it ("; skipped" is added); ``warning``: the
    registry's warning class; ``kind``: its plugins' name in the warnings ("sensor",
    "POS format")."""
    def warn(name: str, value: str, problem: str) -> None:
        warnings.warn(warning(f"{kind} plugin {name!r} ({value}) {problem}; skipped"),
                      stacklevel=4)

    found: dict[str, tuple] = {name: (load_target(t), t) for name, t in builtins.items()}
    for ep in found_points:
        if ep.name in found:
            if found[ep.name][1] != ep.value:
                warn(ep.name, ep.value, f"clashes with {found[ep.name][1]}")
            continue
        try:
            obj = ep.load()
        except BaseException as exc:
            if isinstance(exc, KeyboardInterrupt):   # the user's Ctrl-C
                raise
            warn(ep.name, ep.value, f"failed to load: {type(exc).__name__}: {exc}")
            continue
        problem = check(obj)
        if problem:
            warn(ep.name, ep.value, problem)
            continue
        found[ep.name] = (obj, ep.value)
    return found
