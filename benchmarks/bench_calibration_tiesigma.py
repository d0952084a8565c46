"""How honest the tie points' sigmas are: the transfer error of each tie point (its second
observation minus the true model's projection of the ground under its first: true
parameters, true terrain) against the sigma the matcher gives it, on missions simulated
from the real Autzen orthophoto (4 swings L R L R overlapping by half their width, as
tests/test_reference_ties.py), ties matched with the prior and with the true parameters.

The true geometry is taken twice: with the simulator's noise-free trajectory
(truth/pos.csv: the matching error alone, which the tie sigmas describe) and with the
mission's noisy POS (what an adjustment sees: the POS noise between two swings added,
which the tie variance components estimate). Prints the RMS of error / sigma per axis
(1 when the sigmas are right) over all seeds.

Reproduce:  python benchmarks/bench_calibration_tiesigma.py [--seeds 6 7]
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
AUTZEN = HERE.parent / "tests/data/real/autzen/autzen.jpg"


def transfer_errors(ties, true_models, terrain) -> tuple[np.ndarray, np.ndarray]:
    """(error, sigma) per tie point, (k, 2) each, raw pixels of its second image: the error
    of the second observation given the first, the sigma of that difference (the two
    observations' sigmas, the first's carried into the second image: sqrt(2) x its own)."""
    err, sig = [], []
    for _, g in ties.groupby("tie_id", sort=False):
        a, b = g.iloc[0], g.iloc[1]
        ground = true_models[a.image_id].image_to_ground(np.array([[a.line, a.element]]),
                                                         terrain)
        ij = true_models[b.image_id].ground_to_image(ground, clip=False)[0]
        err.append((b.line - ij[0], b.element - ij[1]))
        sig.append((np.sqrt(2.0) * b.sigma_line, np.sqrt(2.0) * b.sigma_element))
    return np.array(err), np.array(sig)


def one_seed(tmp: Path, seed: int, settings) -> dict:
    from swathflow.calibration.reference import open_reference
    from swathflow.calibration.ties import match_ties
    from swathflow.ingest.mission import load_mission
    from swathflow.rectification.rectify import RawSource
    from swathflow.simulation import simulate
    from swathflow.simulation.reference import degrade_reference
    mission = tmp / f"m{seed}"
    simulate(mission, "tiny", seed=seed, texture=str(AUTZEN), swings_per_strip=4,
             along_overlap=0.5)
    degrade_reference(mission / "truth" / "ortho.tif", mission / "ref.tif", factor=3, seed=1)
    clean = tmp / f"m{seed}_truthpos"
    shutil.copytree(mission, clean)
    toml = clean / "mission.toml"
    toml.write_text(re.sub(r'\[pos\]\nfile = "[^"]*"\nformat = "[^"]*"',
                           '[pos]\nfile = "truth/pos.csv"\nformat = "csv"', toml.read_text()))
    m, mc = load_mission(mission), load_mission(clean)
    doc = json.loads((mission / "truth" / "calibration.json").read_text())["parameters"]
    tp = m.priors.updated({k: {"value": list(v["value"])} for k, v in doc.items()})
    srcs = {i: RawSource(m.image(i).load()) for i in m.image_ids}
    ref = open_reference(mission / "ref.tif")
    out = {}
    for label, params in (("prior", None), ("true", tp)):
        models = {i: m.model(i, params) for i in m.image_ids}
        ties = match_ties(models, srcs, m.terrain, ref, settings, m.gsd)
        for pos, mm in (("noise-free trajectory", mc), ("mission POS", m)):
            true_models = {i: mm.model(i, tp) for i in m.image_ids}
            out[(label, pos)] = transfer_errors(ties, true_models, mc.terrain)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[6, 7])
    ap.add_argument("--factor", type=float, help="tie_sigma_factor (default: the setting's)")
    a = ap.parse_args()
    if not AUTZEN.exists():
        print("autzen.jpg not found: nothing to benchmark")
        return
    import dataclasses
    from swathflow.calibration.reference import DEFAULT_SETTINGS
    settings = DEFAULT_SETTINGS if a.factor is None else dataclasses.replace(
        DEFAULT_SETTINGS, tie_sigma_factor=a.factor)
    t = time.perf_counter()
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in a.seeds:
            for k, v in one_seed(Path(tmp), seed, settings).items():
                runs.setdefault(k, []).append(v)
    print(f"seeds {a.seeds}; tie sigma = hypot({settings.tie_sigma_factor} x the matcher's "
          f"formal sigma, {settings.sigma_floor}); {time.perf_counter() - t:.0f} s")
    print(f"{'ties matched with':<18} {'true geometry with':<22} {'ties':>5} "
          f"{'rms err line/elem (px)':>23} {'rms err/sigma line/elem':>24}")
    for (label, pos), parts in runs.items():
        e = np.concatenate([p[0] for p in parts])
        s = np.concatenate([p[1] for p in parts])
        rms_e = np.sqrt(np.mean(e ** 2, axis=0))
        rms_z = np.sqrt(np.mean((e / s) ** 2, axis=0))
        print(f"{label + ' parameters':<18} {pos:<22} {len(e):5d} "
              f"{rms_e[0]:11.3f} {rms_e[1]:11.3f} {rms_z[0]:12.2f} {rms_z[1]:11.2f}")
    print("command: python benchmarks/bench_calibration_tiesigma.py --seeds "
          + " ".join(map(str, a.seeds)) + (f" --factor {a.factor}" if a.factor else ""))


if __name__ == "__main__":
    main()
