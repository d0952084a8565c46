"""The calibration report as people read it: its figures' data against the mission files,
and the page rendered in a real headless Chromium (Debian's ``chromium``) without console
errors, every figure drawn, screenshot taken."""
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]
CHECK = """<script>
window.addEventListener('load', () => {
  const figs = [...document.querySelectorAll('figure svg')].map(s => {
    const r = s.getBoundingClientRect();
    return [Math.round(r.width), Math.round(r.height), s.querySelectorAll('path,use').length];
  });
  const imgs = [...document.images].map(i => [i.complete, i.naturalWidth]);
  const pre = document.createElement('pre'); pre.id = 'swathflow-check';
  pre.textContent = JSON.stringify({figs, imgs});
  document.body.appendChild(pre);
  console.log('swathflow-check done');
});
</script>"""


@pytest.fixture(scope="module")
def chromium():
    exe = shutil.which("chromium")
    if exe is None:
        r = subprocess.run(["apt-get", "install", "-y", "-q", "chromium"], capture_output=True,
                           text=True, timeout=900, check=False)
        exe = shutil.which("chromium")
        if exe is None:
            pytest.skip(f"chromium not installed and apt-get failed: {r.stderr[-300:]}")
    return exe


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """The simulated paper mission, calibrated: the result and the written files."""
    from swathflow.calibration.control import calibrate
    from swathflow.ingest.mission import load_mission
    from swathflow.sensors.pendulum.simulate import simulate
    root = tmp_path_factory.mktemp("paper")
    simulate(root / "mission", preset="paper", seed=3)
    m = load_mission(root / "mission")
    from swathflow.calibration.report import write_report
    res = calibrate({i: m.model(i) for i in m.images}, m.gcps, m.priors)
    paths = res.write(root / "cal")
    paths["report"] = write_report(res, root / "cal" / "report.html")
    return root / "mission", res, paths


def test_figure_data_is_where_the_points_are(paper):
    """Each residual row carries the observed image position, the ground position and the
    line's time and swing as the mission files give them."""
    mission, res, _ = paper
    r = res.residuals[res.residuals["stage"] == "after"]
    gcp = pd.read_csv(mission / "gcp.csv").set_index(["gcp_id", "image_id"])
    g = gcp.loc[list(zip(r["gcp_id"], r["image_id"]))]
    assert np.allclose(r["line"], g["line"]) and np.allclose(r["element"], g["element"])
    assert np.allclose(r["lon"], g["x"], atol=1e-8) and np.allclose(r["lat"], g["y"], atol=1e-8)
    for iid, grp in r.groupby("image_id"):
        lines = pd.read_csv(mission / "images" / f"{iid}.lines.csv")
        i0 = np.floor(grp["line"].to_numpy()).astype(int)
        f = grp["line"].to_numpy() - i0
        for col, name in (("time", "time"), ("line_swing", "swing")):
            v = lines[name].to_numpy()
            assert np.allclose(grp[col], v[i0] * (1 - f) + v[i0 + 1] * f, atol=1e-6), col


def _chromium(exe, *args, timeout=120):
    return subprocess.run([exe, *FLAGS, *args], capture_output=True, text=True,
                          timeout=timeout, check=False)


def test_report_renders_in_headless_chromium(paper, chromium, tmp_path):
    from PIL import Image
    _, res, paths = paper
    html = Path(paths["report"]).read_text(encoding="utf-8")
    assert "<script" not in html and "<img" not in html     # static, self-contained
    n_images = res.residuals["image_id"].nunique()
    probe = tmp_path / "probe.html"
    probe.write_text(html.replace("</body>", CHECK + "</body>"), encoding="utf-8")
    r = _chromium(chromium, "--enable-logging=stderr", "--v=0", "--virtual-time-budget=5000",
                  "--dump-dom", probe.as_uri())
    assert r.returncode == 0, r.stderr[-2000:]
    console = [ln for ln in r.stderr.splitlines() if ":CONSOLE" in ln]
    assert console and all("swathflow-check done" in ln for ln in console), console
    dom = r.stdout
    i = dom.index('id="swathflow-check">') + len('id="swathflow-check">')
    found = json.loads(dom[i:dom.index("</pre>", i)].replace("&quot;", '"'))
    # map + time + swing + pitch compensation + one per image, each drawn with content
    assert len(found["figs"]) >= 4 + n_images, found
    for w, h, marks in found["figs"]:
        assert w > 300 and h > 150 and marks > 20, found["figs"]
    assert all(done and width > 0 for done, width in found["imgs"])
    shot = tmp_path / "report.png"
    r = _chromium(chromium, "--hide-scrollbars", "--window-size=1280,9000",
                  f"--screenshot={shot}", "file://" + str(paths["report"]))
    assert shot.exists(), r.stderr[-2000:]
    img = np.asarray(Image.open(shot).convert("L"))
    assert img.shape == (9000, 1280)
    inked = (img < 200).mean(axis=1) > 0.01            # rows with drawing or text
    assert inked.mean() > 0.3, inked.mean()


@pytest.fixture(scope="module")
def mosaic_report(tmp_path_factory):
    """A small synthetic mosaic with known strip offsets, and its HTML report."""
    from mosaic_synth import make_swings, random_shifts

    from swathflow.mosaicking.mosaic import mosaic
    d = tmp_path_factory.mktemp("mosaic")
    (d / "swings").mkdir()
    shifts, rads = random_shifts(3, seed=2)
    paths, _, _ = make_swings(d / "swings", n_strips=3, length=360, n_swings=2,
                              shifts=shifts, rads=rads)
    rep = mosaic(paths, d / "mosaic.tif", anchors=["0"], tile=256)
    return d / "mosaic.html", rep, shifts


def test_mosaic_report_tables_carry_the_true_offsets(mosaic_report):
    """The report's node table gives each strip's offset within 0.2 px of the simulated
    shift (strip 0 the anchor) with its sigma; one overlap row per measured overlap."""
    import re
    path, rep, shifts = mosaic_report
    html = path.read_text(encoding="utf-8")
    assert "<script" not in html and "<img" not in html and "http" not in html.split("<svg")[0]
    rows = dict(re.findall(r"<tr><td class='l'>(\d+)</td><td>([^<]+)</td>", html))
    assert sorted(rows) == ["0", "1", "2"]
    for k, text in rows.items():
        off = np.array([float(v) for v in text.split(",")])
        assert np.hypot(*(off - (shifts[int(k)] - shifts[0]))) < 0.2, (k, off, shifts)
    assert html.count("<td class='l'>") == 3 + 2 * len(rep["overlaps"])
    assert len(rep["overlaps"]) >= 2 and sum(o["used"] for o in rep["overlaps"]) >= 2


def test_mosaic_report_renders_in_headless_chromium(mosaic_report, chromium, tmp_path):
    path, _, _ = mosaic_report
    probe = tmp_path / "probe.html"
    probe.write_text(path.read_text(encoding="utf-8").replace("</body>", CHECK + "</body>"),
                     encoding="utf-8")
    r = _chromium(chromium, "--enable-logging=stderr", "--v=0", "--virtual-time-budget=5000",
                  "--dump-dom", probe.as_uri())
    assert r.returncode == 0, r.stderr[-2000:]
    console = [ln for ln in r.stderr.splitlines() if ":CONSOLE" in ln]
    assert console and all("swathflow-check done" in ln for ln in console), console
    dom = r.stdout
    i = dom.index('id="swathflow-check">') + len('id="swathflow-check">')
    found = json.loads(dom[i:dom.index("</pre>", i)].replace("&quot;", '"'))
    assert len(found["figs"]) == 3, found          # graph, residual map, offsets
    for w, h, marks in found["figs"]:
        assert w > 300 and h > 150 and marks > 20, found["figs"]
