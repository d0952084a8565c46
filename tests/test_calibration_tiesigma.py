"""The tie points' sigmas against simulator truth: each tie point's transfer error (its
second observation minus the true model's projection of the ground under its first; true
parameters, true terrain, the simulator's noise-free trajectory) divided by the sigma of
that difference has unit RMS (chi-square bounds), on missions simulated from the real
Autzen orthophoto (4 swings L R L R overlapping by half their width). The matcher's formal
sigma alone is about 1.4 x too small there (benchmarks/bench_calibration_tiesigma.py)."""
from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from scipy import stats

from test_reference_calibration import _mission


def _truth_pos_copy(mission, dest):
    """The mission with the simulator's noise-free trajectory as its POS."""
    shutil.copytree(mission, dest)
    toml = dest / "mission.toml"
    toml.write_text(re.sub(r'\[pos\]\nfile = "[^"]*"\nformat = "[^"]*"',
                           '[pos]\nfile = "truth/pos.csv"\nformat = "csv"', toml.read_text()))
    return dest


def _normalised_errors(tmp, seed):
    from swathflow.calibration.reference import DEFAULT_SETTINGS, open_reference
    from swathflow.calibration.ties import match_ties
    from swathflow.ingest.mission import load_mission
    from swathflow.rectification.rectify import RawSource
    mission, _ = _mission(tmp, seed=seed, factor=3, swings_per_strip=4, along_overlap=0.5)
    m = load_mission(mission)
    clean = load_mission(_truth_pos_copy(mission, tmp / f"clean{seed}"))
    doc = json.loads((mission / "truth" / "calibration.json").read_text())["parameters"]
    tp = m.priors.updated({k: {"value": list(v["value"])} for k, v in doc.items()})
    models = {i: m.model(i, tp) for i in m.image_ids}
    true_models = {i: clean.model(i, tp) for i in m.image_ids}
    ties = match_ties(models, {i: RawSource(m.image(i).load()) for i in m.image_ids},
                      m.terrain, open_reference(mission / "ref.tif"), DEFAULT_SETTINGS, m.gsd)
    z = []
    for _, g in ties.groupby("tie_id", sort=False):
        a, b = g.iloc[0], g.iloc[1]
        ground = true_models[a.image_id].image_to_ground(np.array([[a.line, a.element]]),
                                                         clean.terrain)
        ij = true_models[b.image_id].ground_to_image(ground, clip=False)[0]
        # the first observation's sigma carried into the second image: as its own
        s = np.sqrt(2.0) * np.array([b.sigma_line, b.sigma_element])
        z.append((np.array([b.line, b.element]) - ij) / s)
    return np.array(z)


@pytest.mark.slow
def test_tie_sigmas_describe_the_matching_error(tmp_path):
    z = np.concatenate([_normalised_errors(tmp_path, seed) for seed in (8, 9)])
    n = len(z)
    assert n >= 40, n
    lo, hi = stats.chi2.ppf([0.001, 0.999], n)
    for axis in range(2):
        ss = float(np.sum(z[:, axis] ** 2))
        assert lo < ss < hi, (axis, ss / n, n)
