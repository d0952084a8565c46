"""The sensor-model interface (Community Sensor Model shape).

A *sensor model* is one image's geometry: the plugin's sensor constants, its calibration
parameters, and the image support data (per-line table, trajectory). It is immutable;
``with_parameters`` returns a new model. Coordinates sit on the last axis: image
``(..., 2)`` as (line, element), ground ``(..., 3)`` in ECEF metres (EPSG:4978). Use
:mod:`swathflow.geometry.geodesy` to go to and from latitude, longitude and height.

A plugin is a subclass registered under the entry-point group ``swathflow.sensors``.
It implements :meth:`SensorModel.build`, :meth:`default_parameters`, :meth:`ray`,
:meth:`ground_to_image` and :meth:`image_time`; everything else has a default here.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Any, ClassVar, Mapping

import numpy as np

from swathflow.errors import FormatError
from swathflow.geometry.intersect import intersect
from swathflow.formats.pos import Trajectory
from swathflow.geometry.terrain import Terrain, open_terrain

#: points per pass of the vectorised projections (their temporaries then stay in the CPU
#: cache: about 1.25x faster than one pass over 10^6 points)
CHUNK = 65536


@dataclass(frozen=True)
class Parameter:
    """One named calibration parameter block (a scalar or a small vector)."""

    name: str
    units: str
    value: tuple[float, ...]
    sigma: tuple[float, ...] = ()      # prior sigma per component; inf = no prior
    fixed: tuple[bool, ...] = ()
    description: str = ""

    def __post_init__(self):
        n = len(self.value)
        object.__setattr__(self, "value", tuple(float(v) for v in self.value))
        object.__setattr__(self, "sigma", tuple(float(v) for v in (self.sigma or (np.inf,) * n)))
        object.__setattr__(self, "fixed", tuple(bool(v) for v in (self.fixed or (False,) * n)))
        if not (len(self.sigma) == len(self.fixed) == n):
            raise FormatError(f"parameter {self.name}: value, sigma and fixed need {n} entries")

    @property
    def size(self) -> int:
        return len(self.value)


@dataclass(frozen=True)
class ParameterSet:
    """An ordered, immutable set of parameter blocks with a flat-vector view."""

    blocks: tuple[Parameter, ...]

    def __getitem__(self, name: str) -> np.ndarray:
        return np.array(self.block(name).value)

    def block(self, name: str) -> Parameter:
        for b in self.blocks:
            if b.name == name:
                return b
        raise KeyError(f"no parameter {name!r}; known: {', '.join(self.names)}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.blocks)

    def flat_names(self) -> list[str]:
        return [b.name if b.size == 1 else f"{b.name}[{i}]" for b in self.blocks
                for i in range(b.size)]

    def flat_units(self) -> list[str]:
        return [b.units for b in self.blocks for _ in range(b.size)]

    def vector(self) -> np.ndarray:
        return np.array([v for b in self.blocks for v in b.value])

    def sigmas(self) -> np.ndarray:
        return np.array([v for b in self.blocks for v in b.sigma])

    def fixed_mask(self) -> np.ndarray:
        return np.array([v for b in self.blocks for v in b.fixed])

    def with_vector(self, v) -> "ParameterSet":
        v = np.asarray(v, float)
        if v.size != self.vector().size:
            raise ValueError(f"expected {self.vector().size} values, got {v.size}")
        out, i = [], 0
        for b in self.blocks:
            out.append(replace(b, value=tuple(v[i:i + b.size])))
            i += b.size
        return ParameterSet(tuple(out))

    def updated(self, values: Mapping[str, Any] | None = None, **kw) -> "ParameterSet":
        """New set with some blocks changed: ``name=[...]`` or ``name={"value":..,"sigma":..}``."""
        values = dict(values or {}, **kw)
        unknown = set(values) - set(self.names)
        if unknown:
            raise FormatError(f"unknown parameter(s) {', '.join(sorted(unknown))}; "
                              f"known: {', '.join(self.names)}")
        out = []
        for b in self.blocks:
            if b.name not in values:
                out.append(b)
                continue
            v = values[b.name]
            if isinstance(v, Mapping):
                kw2: dict[str, Any] = {}
                for key in ("value", "sigma", "fixed"):
                    if key in v:
                        x = v[key]
                        x = [x] * b.size if np.isscalar(x) else list(x)
                        if len(x) != b.size:
                            raise FormatError(f"parameter {b.name}.{key}: expected {b.size} "
                                              f"entries, got {len(x)}")
                        kw2[key] = tuple(x)
                out.append(replace(b, **kw2))
            else:
                x = np.atleast_1d(np.asarray(v, float)).ravel()
                if x.size != b.size:
                    raise FormatError(f"parameter {b.name}: expected {b.size} values, "
                                      f"got {x.size}")
                out.append(replace(b, value=tuple(x)))
        return ParameterSet(tuple(out))

    def to_dict(self) -> dict:
        return {b.name: {"value": list(b.value), "sigma": [None if not np.isfinite(s) else s
                                                           for s in b.sigma],
                         "fixed": list(b.fixed), "units": b.units} for b in self.blocks}

    def values_dict(self) -> dict:
        return {b.name: list(b.value) for b in self.blocks}


def _plain(x):
    """JSON-ready copy of nested numpy content."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


class SensorModel(ABC):
    """One image's sensor geometry. Subclasses are immutable and JSON-serialisable."""

    #: registry name (``[sensor] model = ...`` in mission.toml)
    name: ClassVar[str] = ""
    #: ``"whisk-broom"`` or ``"push-broom"`` (information for users and reports)
    kind: ClassVar[str] = ""
    #: keys a mission's ``[sensor]`` table must carry for this model
    required_keys: ClassVar[tuple[str, ...]] = ()
    #: further keys it reads; when given, validation warns on any other key (and names
    #: the nearest known one for a typo)
    optional_keys: ClassVar[tuple[str, ...]] = ()
    #: finite-difference steps per parameter unit (deg, m) for the default partials
    fd_steps: ClassVar[Mapping[str, float]] = {"deg": 1e-4, "m": 1e-4, "": 1e-6}
    #: columns the per-line table (``<id>.lines.csv``) must carry besides ``line``
    line_columns: ClassVar[tuple[str, ...]] = ("time",)
    #: allowed values of an image's ``direction`` key in mission.toml (``None``: free)
    directions: ClassVar[tuple[str, ...] | None] = None

    # --- plugin hooks (what differs between scanners; the framework asks, never branches) --
    @classmethod
    def check_lines(cls, lines: Mapping[str, np.ndarray]) -> list[str]:
        """Problems with one image's per-line table (column -> array), each a sentence
        naming the column and the fix, or a (sentence, fix) pair. The framework has checked already that the
        :attr:`line_columns` are present, numeric and finite, and that ``time`` increases."""
        return []

    @classmethod
    def calibration_strategy(cls) -> Any:
        """The calibration strategy for this scanner: an object with
        ``calibrate(mission, options) -> result`` (``result.write(dir)`` and
        ``result.summary_lines()``), see :mod:`swathflow.calibration.strategy`. ``None``
        (the default) selects the generic control-point adjustment."""
        return None

    @classmethod
    def projector(cls, models) -> Any:
        """Bulk projection for an adjustment: a
        :class:`~swathflow.sensormodel.projection.Projector` over ``models`` (images of this
        sensor) whose ``project(image_index, ground, vectors)`` gives the image coordinates
        of every observation of every image, the parameters of each image passed as a
        vector (no model rebuilt), with the partials by the parameters and the ground
        coordinates. Override it with one vectorised or compiled call and analytic
        partials; the default (:class:`~swathflow.sensormodel.projection.NumericalProjector`)
        works through :meth:`with_vector`, :meth:`ground_to_image` and numerical partials."""
        from swathflow.sensormodel.projection import NumericalProjector
        return NumericalProjector(models)

    @classmethod
    def simulator(cls) -> Any:
        """The scanner's mission simulator, or ``None``: an object with ``presets``
        (names) and ``simulate(out, preset, seed, progress=None, **options) -> truth``,
        see :mod:`swathflow.simulation`."""
        return None

    # --- construction -----------------------------------------------------------------
    def __init__(self, sensor: Mapping[str, Any], lines: Mapping[str, Any],
                 trajectory: Trajectory, params: ParameterSet | Mapping | None = None,
                 _shared: dict | None = None, **image: Any):
        problems = self.check_config(sensor)
        if problems:
            raise FormatError(f"[sensor] for model {self.name!r}: " + "; ".join(problems))
        self._sensor = {k: _plain(v) for k, v in dict(sensor).items()}
        self._lines = {k: np.asarray(v, float) for k, v in dict(lines).items()}
        self._trajectory = trajectory
        base = self.default_parameters(self._sensor)
        if isinstance(params, ParameterSet):
            self._params = params
        else:
            self._params = base.updated(params or {})
        self._image = dict(image)
        # parameter-independent precomputations, shared by every with_parameters() copy
        self._shared = {} if _shared is None else _shared
        self._setup()

    @classmethod
    def build(cls, sensor, lines, trajectory, params=None, **image) -> "SensorModel":
        """The factory the registry calls: ``sensor`` is the mission's ``[sensor]`` table,
        ``lines`` the per-line table (column -> array), ``trajectory`` a
        :class:`~swathflow.formats.pos.Trajectory`, ``image`` the image's attributes (direction...)."""
        return cls(sensor, lines, trajectory, params, **image)

    @classmethod
    def check_config(cls, sensor: Mapping[str, Any]) -> list[str]:
        """Problems with a ``[sensor]`` table, each a sentence (empty when fine)."""
        return [f"missing key {k!r}" for k in cls.required_keys if k not in sensor]

    @classmethod
    @abstractmethod
    def default_parameters(cls, sensor: Mapping[str, Any]) -> ParameterSet:
        """The calibration parameters with their default values and prior sigmas."""

    def _setup(self) -> None:  # noqa: B027 - an optional hook, empty by default
        """Precompute per-image quantities (called once by ``__init__``)."""

    # --- state ----------------------------------------------------------------------------
    @property
    def parameters(self) -> ParameterSet:
        return self._params

    @property
    def sensor(self) -> dict:
        return dict(self._sensor)

    @property
    def lines(self) -> dict:
        return dict(self._lines)

    @property
    def trajectory(self) -> Trajectory:
        return self._trajectory

    @property
    def image_attrs(self) -> dict:
        return dict(self._image)

    @property
    def n_lines(self) -> int:
        return int(len(self._lines["time"]))

    @property
    def n_elements(self) -> int:
        return int(self._sensor["n_elements"])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_lines, self.n_elements)

    def with_parameters(self, params: ParameterSet | Mapping | None = None, **kw) -> "SensorModel":
        """A new model with some parameters changed (by name, or a whole ParameterSet)."""
        new = params if isinstance(params, ParameterSet) else self._params.updated(params, **kw)
        return type(self)(self._sensor, self._lines, self._trajectory, new,
                          _shared=self._shared, **self._image)

    def with_vector(self, v) -> "SensorModel":
        return self.with_parameters(self._params.with_vector(v))

    def to_state(self) -> dict:
        """A JSON-ready dict from which :meth:`from_state` rebuilds an equal model.

        The trajectory is cut to the image's time span (plus a margin)."""
        t0, t1 = self._lines["time"].min(), self._lines["time"].max()
        # whisk-broom models time every pixel: keep the POS up to the image's last pixel
        corners = self.image_time(np.array([[0.0, 0.0], [0.0, self.n_elements - 1.0],
                                            [self.n_lines - 1.0, 0.0],
                                            [self.n_lines - 1.0, self.n_elements - 1.0]]))
        t0, t1 = min(t0, np.nanmin(corners)), max(t1, np.nanmax(corners))
        tr = self._trajectory
        i0 = max(int(np.searchsorted(tr.time, t0)) - 2, 0)
        i1 = min(int(np.searchsorted(tr.time, t1)) + 2, tr.time.size)
        ds = tr.to_dataset().isel(time=slice(i0, i1))
        return {"model": self.name, "format": "swathflow-sensor-state/1",
                "sensor": _plain(self._sensor),
                "parameters": self._params.to_dict(),
                "lines": _plain(self._lines),
                "trajectory": {"max_gap": tr.max_gap,
                               **{k: ds[k].values.tolist() for k in
                                  ("time", "lat", "lon", "h", "roll", "pitch", "heading")}},
                "image": _plain(self._image)}

    @classmethod
    def from_state(cls, state: Mapping) -> "SensorModel":
        import xarray as xr
        from swathflow.formats.pos import POS_VARIABLES
        tr = state["trajectory"]
        ds = xr.Dataset({k: ("time", np.asarray(tr[k], float)) for k in POS_VARIABLES},
                        coords={"time": np.asarray(tr["time"], float)})
        traj = Trajectory.from_dataset(ds, max_gap=tr.get("max_gap", 1.0))
        params = cls.default_parameters(state["sensor"]).updated(
            {k: {"value": v["value"],
                 "sigma": [np.inf if s is None else s for s in v["sigma"]],
                 "fixed": v["fixed"]} for k, v in state["parameters"].items()})
        return cls(state["sensor"], state["lines"], traj, params, **state.get("image", {}))

    def token(self) -> str:
        """A stable content hash of the model (sensor, parameters, support data)."""
        h = hashlib.sha256(json.dumps(self.to_state(), sort_keys=True).encode())
        return h.hexdigest()

    def __dask_tokenize__(self):
        return (type(self).__qualname__, self.token())

    def __repr__(self) -> str:
        return (f"<{type(self).__name__} {self.name!r} {self.n_lines}x{self.n_elements} "
                f"{self._image}>")

    # --- geometry ---------------------------------------------------------------------
    @abstractmethod
    def ray(self, image) -> tuple[np.ndarray, np.ndarray]:
        """Origin and unit direction (ECEF, ``(..., 3)`` each) of the ray of image points."""

    @abstractmethod
    def ground_to_image(self, ground, clip: bool = True) -> np.ndarray:
        """Continuous image coordinates ``(..., 2)`` of ECEF ground points.

        NaN where the point is not seen: the image's lines never sweep it, it lies behind
        the sensor, or (with ``clip``) it falls off the detector. ``clip=False`` keeps
        coordinates beyond the detector's ends (calibration needs them)."""

    @abstractmethod
    def image_time(self, image) -> np.ndarray:
        """Acquisition time (s, POS time scale) of image points ``(..., 2)``."""

    def image_to_ground(self, image, terrain: Terrain | float | str = 0.0) -> np.ndarray:
        """ECEF ground points ``(..., 3)`` of image points on the terrain (a constant
        ellipsoidal height, a DEM path or a :class:`~swathflow.geometry.terrain.Terrain`).

        Rays that miss the terrain give NaN; their count is reported as a warning. Large
        inputs go through in chunks of ``CHUNK`` points (the temporaries stay in cache)."""
        image = np.asarray(image, float)
        terrain = open_terrain(terrain)
        flat = image.reshape(-1, 2)
        out = np.empty((flat.shape[0], 3))
        for s in range(0, flat.shape[0], CHUNK):
            origin, direction = self.ray(flat[s:s + CHUNK])
            out[s:s + CHUNK] = intersect(origin, direction, terrain)
        out = out.reshape(image.shape[:-1] + (3,))
        missed = int(np.count_nonzero(np.isnan(out).any(axis=-1)))
        if missed:
            warnings.warn(RayMissWarning(f"{missed} of {out.size // 3} rays missed the terrain"),
                          stacklevel=2)
        return out

    def sensor_position(self, time) -> np.ndarray:
        """Projection centre (ECEF) at times ``time`` (for a line scanner: of that line)."""
        return self.ray(self._time_to_image(time))[0]

    def sensor_attitude(self, time) -> np.ndarray:
        """Rotation from the sensor frame S to ECEF, ``(..., 3, 3)``, at times ``time``."""
        raise NotImplementedError(f"{self.name} does not expose its attitude")

    def _time_to_image(self, time) -> np.ndarray:
        t = np.asarray(time, float)
        lt = self._lines["time"]
        order = np.argsort(lt)
        line = np.interp(t, lt[order], np.arange(lt.size, dtype=float)[order],
                         left=np.nan, right=np.nan)
        return np.stack(np.broadcast_arrays(line, (self.n_elements - 1) / 2.0), axis=-1)

    # --- partial derivatives ------------------------------------------------------------------
    def parameter_partials(self, ground, names: list[str] | None = None) -> np.ndarray:
        """d(line, element)/d(parameter), ``(..., 2, P)`` over the flat parameters
        (all, or the flat ``names``), by central differences of :meth:`ground_to_image`."""
        ground = np.asarray(ground, float)
        flat = self._params.flat_names()
        units = self._params.flat_units()
        sel = range(len(flat)) if names is None else [flat.index(n) for n in names]
        v0 = self._params.vector()
        cols = []
        for i in sel:
            h = self.fd_steps.get(units[i], self.fd_steps.get("", 1e-6))
            vp, vm = v0.copy(), v0.copy()
            vp[i] += h
            vm[i] -= h
            ip = self.with_vector(vp).ground_to_image(ground, clip=False)
            im = self.with_vector(vm).ground_to_image(ground, clip=False)
            cols.append((ip - im) / (2 * h))
        return np.stack(cols, axis=-1)

    def ground_partials(self, ground, step: float = 0.01) -> np.ndarray:
        """d(line, element)/d(X, Y, Z) in ECEF, ``(..., 2, 3)``, by central differences."""
        ground = np.asarray(ground, float)
        cols = []
        for i in range(3):
            d = np.zeros(3)
            d[i] = step
            cols.append((self.ground_to_image(ground + d, clip=False)
                         - self.ground_to_image(ground - d, clip=False)) / (2 * step))
        return np.stack(cols, axis=-1)


class RayMissWarning(UserWarning):
    """Some rays did not meet the terrain (their ground points are NaN)."""
