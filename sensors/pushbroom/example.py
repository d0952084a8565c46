"""A realistic three-line camera and flight for contract tests, docs and benchmarks."""
from __future__ import annotations

import numpy as np

from swathflow.sensors.pushbroom.viewing import THREE_LINE_VIEWS


def example_sensor() -> dict:
    """The three-line camera of :meth:`PushbroomModel.example_model` as a ``[sensor]`` dict."""
    rng = np.random.default_rng(8)
    seg = [0, 1024, 2048]

    def aps():
        # smooth APs: one cubic over the whole line, re-expanded per segment (C0/C1 hold)
        c = rng.normal(0, 1, 4) * np.array([2e-4, 1e-7, 1e-11, 1e-14])
        out = []
        for s0 in seg:
            # p(s0 + ds) = sum c_m (s0 + ds)^m -> coefficients in ds
            a0 = c[0] + c[1] * s0 + c[2] * s0 ** 2 + c[3] * s0 ** 3
            a1 = c[1] + 2 * c[2] * s0 + 3 * c[3] * s0 ** 2
            a2 = c[2] + 3 * c[3] * s0
            out.append([a0, a1, a2, c[3]])
        return out

    v = {name: {"psi_x0_deg": psi, "ax": aps(), "bx": aps()}
         for name, psi in THREE_LINE_VIEWS.items()}
    return {"model": "pushbroom", "n_elements": 3072, "segments": seg, "pixel_pitch": 1e-5,
            "focal_length": 0.1, "s_c": 1535.5, "views": v,
            "fixes": {"time": [1000.0, 1005.0, 1010.0],
                      "d_ned": [[0.1, -0.2, 0.05], [-0.1, 0.15, 0.0], [0.05, 0.0, -0.1]],
                      "d_opk": [[0.002, -0.001, 0.003], [0.0, 0.002, -0.002],
                                [-0.001, 0.0, 0.001]]}}


def example_trajectory(t0: float = 995.0, t1: float = 1015.0, lat0: float = 34.0,
                       lon0: float = 113.0, h: float = 2080.0, speed: float = 60.0,
                       heading: float = 30.0, rate: float = 200.0):
    """A straight flight line with a gentle attitude wobble, as a Trajectory."""
    import xarray as xr
    from swathflow.formats.pos import Trajectory
    t = np.arange(t0, t1 + 0.5 / rate, 1.0 / rate)
    d = speed * (t - t0)
    R = 6378137.0
    hd = np.radians(heading)
    lat = lat0 + np.degrees(d * np.cos(hd) / R)
    lon = lon0 + np.degrees(d * np.sin(hd) / (R * np.cos(np.radians(lat0))))
    roll = 0.3 * np.sin(2 * np.pi * 0.21 * (t - t0))
    pitch = 1.5 + 0.2 * np.sin(2 * np.pi * 0.13 * (t - t0) + 1.0)
    hdg = heading + 0.4 * np.sin(2 * np.pi * 0.07 * (t - t0))
    ds = xr.Dataset({"lat": ("time", lat), "lon": ("time", lon), "h": ("time", np.full_like(t, h)),
                     "roll": ("time", roll), "pitch": ("time", pitch),
                     "heading": ("time", (hdg + 180) % 360 - 180)}, coords={"time": t})
    return Trajectory.from_dataset(ds)


def example_image(cls, view: str = "nadir", n_lines: int = 600):
    """One image of the example camera (``cls`` is the model class)."""
    line_period = 0.2 / 60.0   # one ground sample (0.2 m at 2000 m) per line at 60 m/s
    time = 1003.0 + line_period * np.arange(n_lines)
    return cls.build(example_sensor(), {"time": time}, example_trajectory(), None,
                     image_id=f"{view}-1", view=view, strip=1)
