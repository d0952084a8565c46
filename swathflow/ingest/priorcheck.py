"""The ``[calibration]`` priors of mission.toml: finite values, angles within a turn,
sigmas finite and >= 0. A sigma of 0 holds that component at its value (as ``--fix``
does): it is not weighted infinitely but marked fixed; an absent sigma keeps the sensor
plugin's default."""
from __future__ import annotations

import math

#: the largest magnitude of a prior angle (degrees): beyond a turn, a unit mistake
MAX_ANGLE_DEG = 360.0


def _numbers(x) -> list | None:
    """The numbers of a scalar or a list (None: something else)."""
    xs = x if isinstance(x, list) else [x]
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in xs):
        return [float(v) for v in xs]
    return None


def check_prior(name, v, toml, c) -> None:
    """A ``[calibration]`` entry: finite values; sigmas finite and >= 0 (0 holds the
    parameter at its value, as ``--fix`` does; leave sigma out for no prior)."""
    where = f"[calibration].{name}"
    value = v.get("value") if isinstance(v, dict) else v
    sigma = v.get("sigma") if isinstance(v, dict) else None
    vals = _numbers(value) if value is not None else []
    if vals is None or not all(math.isfinite(x) for x in vals):
        c.add(toml, where + ".value", f"must be finite numbers, got {value!r}",
              "value = [0.0, 0.0, 0.0]")
    if sigma is not None:
        sig = _numbers(sigma)
        if sig is None or not all(math.isfinite(x) and x >= 0 for x in sig):
            c.add(toml, where + ".sigma", f"must be finite numbers >= 0, got {sigma!r}",
                  "sigma = [1.0, 1.0, 1.0] (0 holds the parameter at its value, like "
                  "--fix; leave sigma out for no prior)")


def held(params, toml, c):
    """Prior sigma 0: the component is held at its value (``fixed``), not weighted
    infinitely; a prior angle beyond a turn is an error (a unit mistake)."""
    from dataclasses import replace

    from swathflow.sensormodel.base import ParameterSet
    blocks = []
    for b in params.blocks:
        if b.units == "deg" and any(abs(x) > MAX_ANGLE_DEG for x in b.value):
            c.add(toml, f"[calibration].{b.name}.value", f"{list(b.value)} degrees: beyond "
                  f"+-{MAX_ANGLE_DEG:.0f} degrees", "give the angles in degrees")
        if any(s == 0 for s in b.sigma):
            b = replace(b, fixed=tuple(f or s == 0 for f, s in zip(b.fixed, b.sigma)))
        blocks.append(b)
    return ParameterSet(tuple(blocks))
