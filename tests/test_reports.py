"""The reports as a photogrammetrist reads them: ground errors in metres against the
simulator's truth, the overlap graph drawing every overlap, the map frames' units, the
pages from autoescaped templates, figures from matplotlib without pyplot."""
import re
from pathlib import Path
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The simulated tiny mission (no images rendered), calibrated from its control
    points."""
    from swathflow.calibration.control import calibrate
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pendulum.simulate import simulate
    root = tmp_path_factory.mktemp("tiny")
    simulate(root / "mission", preset="tiny", seed=3, render=False)
    m = load_mission(root / "mission")
    models = {i: m.model(i) for i in m.images}
    res = calibrate(models, m.gcps, m.priors)
    return m, models, res


def _enu(ref_ecef, ecef):
    """East, north, up (m) of ``ecef`` from ``ref_ecef`` (pyproj's geodetic, own rotation)."""
    import pyproj
    lon, lat, _ = pyproj.Transformer.from_crs(4978, 4979, always_xy=True).transform(
        *ref_ecef.T)
    la, lo = np.radians(lat), np.radians(lon)
    d = ecef - ref_ecef
    e = -np.sin(lo) * d[:, 0] + np.cos(lo) * d[:, 1]
    n = (-np.sin(la) * np.cos(lo) * d[:, 0] - np.sin(la) * np.sin(lo) * d[:, 1]
         + np.cos(la) * d[:, 2])
    u = np.cos(la) * np.cos(lo) * d[:, 0] + np.cos(la) * np.sin(lo) * d[:, 1] + np.sin(la) * d[:, 2]
    return e, n, u


def _truth_errors(m, models, res, stage="after"):
    """Each single-ray point's ground error, computed apart from the report: the observed
    pixel cast onto the surveyed point's ellipsoidal height with the adjusted model
    (``image_to_ground``), minus the surveyed position, in east/north metres."""
    import pyproj
    g = m.gcps
    vec = res.image_vectors if stage == "after" else {
        i: models[i].parameters.vector() for i in models}
    rows = []
    to_llh = pyproj.Transformer.from_crs(4978, 4979, always_xy=True)
    for (gid, iid), grp in g.groupby(["gcp_id", "image_id"]):
        xyz = grp[["X", "Y", "Z"]].to_numpy(float)
        h = to_llh.transform(*xyz.T)[2][0]
        model = models[iid].with_vector(vec[iid])
        got = model.image_to_ground(grp[["line", "element"]].to_numpy(float), terrain=float(h))
        e, n, _ = _enu(xyz, got)
        rows.append({"gcp_id": gid, "role": grp["role"].iloc[0], "east": e[0], "north": n[0]})
    return pd.DataFrame(rows)


def test_accuracy_table_is_the_truth_rmse(tiny):
    """The report's RMSE_E, RMSE_N, RMSE_H and mean per role after the adjustment equal
    those of the ground errors computed from the simulator's control points by casting
    each observed pixel onto the surveyed height (within 5 mm; the report linearises)."""
    from swathflow.calibration.accuracy import accuracy_table, point_errors
    m, models, res = tiny
    assert m.gcps.groupby("gcp_id").size().max() == 1            # single rays here
    truth = _truth_errors(m, models, res)
    pts = point_errors(res.residuals)
    acc = accuracy_table(pts, res.residuals).set_index(["stage", "role"])
    for role in ("control", "check"):
        t = truth[truth["role"] == role]
        assert len(t) > 0
        row = acc.loc[("after", role)]
        assert row["points"] == len(t)
        rmse_e = np.sqrt(np.mean(t["east"] ** 2))
        rmse_n = np.sqrt(np.mean(t["north"] ** 2))
        assert row["RMSE_E"] == pytest.approx(rmse_e, abs=5e-3)
        assert row["RMSE_N"] == pytest.approx(rmse_n, abs=5e-3)
        assert row["RMSE_H"] == pytest.approx(np.hypot(rmse_e, rmse_n), abs=5e-3)
        assert row["mean_E"] == pytest.approx(t["east"].mean(), abs=5e-3)
        assert row["max_H"] == pytest.approx(np.hypot(t["east"], t["north"]).max(), abs=5e-3)
        assert row["H95"] == pytest.approx(1.7308 * row["RMSE_H"])
        assert np.isnan(row["RMSE_U"]) and row["with_up"] == 0     # up not observed
    # the pixel figures beside them are the residuals' RMS
    after = res.residuals[(res.residuals["stage"] == "after")
                          & (res.residuals["role"] == "check")]
    assert acc.loc[("after", "check"), "rms_x_px"] == pytest.approx(
        np.sqrt(np.mean(after["x"] ** 2)))


def test_a_known_survey_shift_shows_in_metres(tiny):
    """Moving the check points' surveyed positions 3 m east and 2 m south (the images
    unchanged) moves their ground errors by -3 m east and +2 m north: metres, signs
    (image-derived minus surveyed) and axes as labelled."""
    from swathflow.calibration.accuracy import enu_basis, point_errors
    from swathflow.calibration.result import residual_table
    m, models, res = tiny
    obs = m.gcps.copy()
    chk = obs["role"] == "check"
    r = res.residuals
    ll = r[r["stage"] == "after"].set_index("row")[["lat", "lon"]].loc[obs.index[chk]]
    basis = enu_basis(ll["lat"].to_numpy(), ll["lon"].to_numpy())
    shift = 3.0 * basis[:, 0, :] - 2.0 * basis[:, 1, :]
    obs.loc[chk, ["X", "Y", "Z"]] = obs.loc[chk, ["X", "Y", "Z"]].to_numpy() + shift
    before = point_errors(residual_table(models, res.image_vectors, m.gcps, "after"))
    after = point_errors(residual_table(models, res.image_vectors, obs, "after"))
    b = before.set_index("gcp_id")
    a = after.set_index("gcp_id")
    ids = a.index[a["role"] == "check"]
    np.testing.assert_allclose(a.loc[ids, "east"] - b.loc[ids, "east"], -3.0, atol=0.02)
    np.testing.assert_allclose(a.loc[ids, "north"] - b.loc[ids, "north"], 2.0, atol=0.02)
    ctl = a.index[a["role"] == "control"]
    np.testing.assert_allclose(a.loc[ctl, "east"], b.loc[ctl, "east"])


def test_multi_ray_points_get_up():
    """A point seen in two images with rays crossing at an angle gets east, north and up
    back from its residuals (the space intersection); one seen once gets no up."""
    from swathflow.calibration.accuracy import JACOBIAN, point_errors
    rng = np.random.default_rng(4)
    d_true = np.array([0.3, -0.2, 0.8])
    rows = []
    for k, tilt in enumerate((-0.4, 0.5)):               # left and right looks
        J = np.array([[0.02, 1.0, tilt], [1.0, -0.01, 0.03]]) + 0.01 * rng.normal(size=(2, 3))
        r = J @ d_true                                    # (line, element) residual
        rows.append({"gcp_id": "P", "image_id": f"I{k}", "stage": "after", "role": "check",
                     "y": r[0], "x": r[1], **dict(zip(JACOBIAN, J.ravel()))})
    rows.append({**rows[0], "gcp_id": "Q"})
    pts = point_errors(pd.DataFrame(rows)).set_index("gcp_id")
    np.testing.assert_allclose(pts.loc["P", ["east", "north", "up"]].to_numpy(float), d_true,
                               atol=1e-9)
    assert pts.loc["P", "rays"] == 2 and np.isnan(pts.loc["Q", "up"])


def _layout_and_report():
    """Two strips of three swings each; overlaps inside the strips and across them, one
    skipped and one rejected; node 0 the anchor."""
    from affine import Affine

    from swathflow.mosaicking.inputs import Layout, Swing
    sw = [Swing(f"s{k}.tif", f"S{s}_{q}", s, q * 80, s * 90, 100, 120, None, "uint8")
          for k, (s, q) in enumerate((s, q) for s in range(2) for q in range(3))]
    layout = Layout("EPSG:32633", Affine(0.5, 0, 500000.0, 0, -0.5, 4100000.0), (340, 210),
                    sw)
    pairs = [("S0_0", "S0_1"), ("S0_1", "S0_2"), ("S1_0", "S1_1"), ("S1_1", "S1_2"),
             ("S0_0", "S1_0"), ("S0_1", "S1_1"), ("S0_2", "S1_2"), ("S0_1", "S1_0")]
    overlaps = []
    for q, (a, b) in enumerate(pairs):
        ok, used = q != 6, q not in (6, 7)
        overlaps.append({"ref": a, "mov": b, "window": [q * 20, 60, q * 20 + 30, 110],
                         "ok": ok, "used": used, "status": "ok" if ok else "low_texture",
                         "offset": [0.1 * q, -0.2], "sigma": [0.02, 0.03], "pixels": 900,
                         "residual": [0.01 * q, -0.02] if used else [None, None]})
    rep = {"per_image": False, "anchor": "images", "anchors": ["0"], "sigma0": 0.8,
           "grid": {"crs": "EPSG:32633", "res": 0.5}, "overlaps": overlaps,
           "skipped": [o for o in overlaps if not o["ok"]],
           "rejected": [o for o in overlaps if o["ok"] and not o["used"]],
           "nodes": [{"node": "0", "offset": [0.0, 0.0], "sigma": [None, None],
                      "radiometric": 0.0},
                     {"node": "1", "offset": [2.0, -4.0], "sigma": [0.05, 0.1],
                      "radiometric": -3.5}]}
    return layout, rep


def test_every_overlap_is_an_edge_of_the_graph():
    """One edge per overlap (also between swings of one strip, which the per-strip nodes
    drew as a point), from the ref swing's centre to the mov swing's, in map metres."""
    from swathflow.mosaicking.report import graph_edges
    layout, rep = _layout_and_report()
    edges = graph_edges(rep, layout)
    assert [(e["ref"], e["mov"]) for e in edges] == [(o["ref"], o["mov"])
                                                     for o in rep["overlaps"]]
    centre = {s.image_id: (500000.0 + 0.5 * (s.col + s.width / 2),
                           4100000.0 - 0.5 * (s.row + s.height / 2)) for s in layout.swings}
    for e in edges:
        assert e["a"] == pytest.approx(centre[e["ref"]]) and e["b"] == pytest.approx(
            centre[e["mov"]])
        assert np.hypot(e["a"][0] - e["b"][0], e["a"][1] - e["b"][1]) > 1.0
    assert [e["state"] for e in edges].count("skipped") == 1
    assert [e["state"] for e in edges].count("rejected") == 1


def _texts(fig):
    return [t.get_text() for ax in fig.axes for t in
            (ax.get_legend().get_texts() if ax.get_legend() else [])]


def test_graph_and_map_name_only_what_they_draw_in_metres():
    """Legends name what is drawn (an anchor square only with an anchor; rejected and
    skipped entries only when there are such overlaps); the map frames are in the grid's
    CRS with metre coordinates, a scale bar and a north arrow."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from swathflow.mosaicking.report import graph_figure, map_figure
    layout, rep = _layout_and_report()
    grey = np.full((2, 170, 105), 200, np.uint8)
    for fig in (graph_figure(rep, layout), map_figure(rep, grey, layout)):
        ax = fig.axes[0]
        assert "easting (m)" in ax.get_xlabel() and "EPSG:32633" in ax.get_xlabel()
        assert ax.get_ylabel() == "northing (m)"
        assert ax.get_xlim() == pytest.approx((500000.0, 500105.0))
        assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)
        assert any(t.get_text() == "N" for t in ax.texts)
    texts = _texts(graph_figure(rep, layout))
    assert "anchor node" in texts and "rejected overlap" in texts and "skipped overlap" in texts
    clean = dict(rep, anchors=[], overlaps=[o for o in rep["overlaps"] if o["used"]])
    texts = _texts(graph_figure(clean, layout))
    assert not {"anchor node", "rejected overlap", "skipped overlap"} & set(texts)


def test_report_picture_is_a_png_of_the_figure(tmp_path):
    from PIL import Image

    from swathflow.mosaicking.report import seams_picture
    layout, rep = _layout_and_report()
    grey = np.full((2, 170, 105), 200, np.uint8)
    path = seams_picture(tmp_path / "m.tif", rep, layout, tmp_path / "m.report.png", grey, 2.0)
    with Image.open(path) as im:
        assert im.format == "PNG"
        w, h = im.size
        im.verify()
    assert 1000 <= w <= 2200 and 600 <= h <= 1200, (w, h)        # about 15 x 7.5 in at 100 dpi
    assert not list(tmp_path.glob("*.part*"))                   # written atomically


def test_mosaic_page_tables_in_pixels_and_metres(tmp_path):
    """The node and overlap tables give offsets in grid pixels and on the ground (east =
    column x pixel size, north = -row x pixel size); the anchor's sigma reads "anchor";
    no template marker is left and every section is there."""
    from swathflow.mosaicking.report_html import mosaic_report_html
    layout, rep = _layout_and_report()
    grey = np.full((2, 170, 105), 200, np.uint8)
    html = open(mosaic_report_html(tmp_path / "m.tif", rep, layout, tmp_path / "m.html",
                                   grey, 2.0)).read()
    assert "{{" not in html and "{%" not in html and "None" not in html.split("<svg")[0]
    for head in ("Overlap graph", "Residuals on the map", "Offsets", "Nodes", "Overlaps"):
        assert f"<h2>{head}</h2>" in html
    rows = re.findall(r"<tr><td class='l'>(\d)</td><td>([^<]+)</td><td>([^<]+)</td>"
                      r"<td>([^<]+)</td>", html)
    assert [r[0] for r in rows] == ["0", "1"]
    assert rows[1][1] == "2.000, -4.000" and rows[1][2] == "-2.000, -1.000"
    assert rows[0][3] == "anchor"
    assert html.count("<svg") == 3 and "<script" not in html
    assert "overflow-x:auto" in html


def test_pages_are_autoescaped():
    from swathflow.pages import render, table
    page = render("table.html.j2", t=table(pd.DataFrame({"name": ["<script>x</script>"],
                                                        "v": [1.5]}), left=("name",)))
    assert "<script>" not in page and "&lt;script&gt;" in page


def test_calibration_page_sections_and_units(tiny, tmp_path):
    from swathflow.calibration.report import write_report
    _, _, res = tiny
    html = open(write_report(res, tmp_path / "report.html"), encoding="utf-8").read()
    assert "{{" not in html and "{%" not in html
    for head in ("Ground accuracy of the control and check points", "Parameters",
                 "Correlation matrix", "Residual statistics per image",
                 "Ground errors on the map", "Residual vectors per image"):
        assert f"<h2>{head}</h2>" in html, head
    assert "RMSE_E <span class=\"u\">(m)</span>" in html
    assert "rms_x_px <span class=\"u\">(px)</span>" in html
    assert "from 120.4" not in html and "easting (m)" in html and "UTM zone" in html
    assert '<div class="scroll"><table>' in html


def test_no_pyplot_and_no_matplotlib_at_import():
    """matplotlib is imported where a report is made, never at package import, and the
    reports never touch pyplot's global state."""
    code = ("import sys, swathflow, swathflow.calibration.result, "
            "swathflow.mosaicking.mosaic, swathflow.flows.mission; "
            "print('matplotlib' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "False"
    # a report drawn in a fresh interpreter (this one may hold pyplot from another test,
    # e.g. xarray's .plot): matplotlib imported, pyplot not
    code = ("import sys; sys.path.insert(0, {here!r}); "
            "from test_reports import _layout_and_report; "
            "from swathflow.mosaicking.report import graph_figure; "
            "layout, rep = _layout_and_report(); graph_figure(rep, layout); "
            "print('matplotlib' in sys.modules, 'matplotlib.pyplot' in sys.modules)"
            ).format(here=str(Path(__file__).parent))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "True False"


def test_reports_drawn_on_threads_leave_matplotlib_settings_as_they_were():
    """The flow draws reports on threads beside its other work: matplotlib's settings (one
    dictionary a process) are the user's again afterwards, whatever the interleaving."""
    import threading

    import matplotlib
    from swathflow.drawing import svg
    from swathflow.mosaicking.report import graph_figure
    before = dict(matplotlib.rcParams)
    layout, rep = _layout_and_report()
    threads = [threading.Thread(target=lambda: svg(graph_figure(rep, layout)))
               for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    after = dict(matplotlib.rcParams)
    assert {k: v for k, v in after.items() if before.get(k) != v} == {}
