"""Command handlers: each turns parsed arguments into plain typed calls of the stage
functions and prints what a person reads. Stage functions print nothing; they report
progress through a ``progress`` callback (a line of text)."""
from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path

from swathflow.errors import SwathflowError


def _say(args):
    """The progress callback of a command: a line on stdout unless ``--quiet``."""
    if getattr(args, "quiet", False):
        return None
    return lambda line: print(line, flush=True)


def _echo(args, *parts, **kw) -> None:
    """print, unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(*parts, **kw)


def _ids(text: str | None) -> tuple[str, ...] | None:
    if not text:
        return None
    return tuple(s.strip() for s in text.split(",") if s.strip()) or None


def validate(args) -> int:
    """``swathflow validate MISSION``: every problem with its fix; exit 2 if any."""
    from swathflow.ingest.mission import format_problems, inspect_mission
    problems, p = inspect_mission(args.mission)
    if not [pr for pr in problems if pr.level != "warning"]:
        from swathflow.flows.guard import band_problems
        problems += band_problems(p)        # what rectify would refuse
    errors = [pr for pr in problems if pr.level != "warning"]
    if errors:
        print(format_problems(args.mission, problems))
        return 2
    for pr in problems:                 # warnings only: the mission is usable
        if not getattr(args, "quiet", False):
            print(f"swathflow validate: warning: {pr.text()}", file=sys.stderr)
    n = 0 if p["gcps"] is None else len(p["gcps"])
    _echo(args, f"mission {args.mission}: OK ({len(p['images'])} images, {n} GCP observations, "
          f"sensor {p['sensor'].get('model')}, output {p['crs']} at {p['gsd']} m"
          + (f", {len(problems)} warning(s)" if problems else "") + ")")
    return 0


def simulation_options(args) -> dict:
    """Simulator options given on the command line (the simulator checks them)."""
    keys = ("texture", "dem", "gcp_noise", "gross_fraction", "image_format", "pos_format",
            "direction_omega")
    out = {k: getattr(args, k) for k in keys if getattr(args, k, None) is not None}
    if getattr(args, "no_direction_effect", False):
        out["direction_effect"] = False
    if getattr(args, "geometry_only", False):
        out["render"] = False
        out["write_ortho"] = False
    if getattr(args, "render", False):
        out["render"] = True
        out["write_ortho"] = True
    return out


def _check_out_free(out, force: bool) -> None:
    """Refuse to write a simulation over an existing mission or a non-empty folder."""
    from pathlib import Path

    from swathflow.errors import SwathflowError
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise SwathflowError(f"{out}: exists and is not a folder; give a new folder name")
    if p.is_dir() and any(p.iterdir()) and not force:
        what = "a mission" if (p / "mission.toml").exists() else "files"
        raise SwathflowError(f"{out}: already holds {what}; simulating into it would replace "
                             f"its POS and images: give a new folder, or add --force")


def simulate(args) -> int:
    """``swathflow simulate OUT --preset NAME --seed N``."""
    from swathflow.simulation import simulate as run
    _check_out_free(args.out, getattr(args, "force", False))
    t0 = time.perf_counter()
    truth = run(args.out, args.preset, args.seed, progress=_say(args),
                **simulation_options(args))
    n_obs = sum(v["control"] + v["check"] for v in truth["gcp_counts"].values())
    ties = truth.get("tie_observations")
    _echo(args, f"wrote {args.out}: {len(truth['images'])} images, {n_obs} GCP "
          f"{'and ' + str(ties) + ' tie ' if ties else ''}observations, "
          f"{'rendered' if truth['images_rendered'] else 'geometry only'}, "
          f"in {time.perf_counter() - t0:.1f} s (truth in {os.path.join(args.out, 'truth')})")
    return 0


def calibrate(args) -> int:
    """``swathflow calibrate MISSION --out DIR``: the sensor plugin's calibration strategy."""
    from swathflow.calibration.strategy import CalibrationOptions, calibrate_mission
    from swathflow.ingest.mission import load_mission
    mission = load_mission(args.mission)
    options = CalibrationOptions(
        fixed=tuple(args.fix or ()), images=_ids(args.images), robust=not args.no_robust,
        vce=not args.no_vce, vce_priors=args.vce_priors, sigma_px=args.sigma_px,
        shared_boresight=(args.model == "12"), drift=args.drift,
        reference=args.reference, reference_dem=args.reference_dem, max_rounds=args.rounds,
        ties=args.ties,
        extra={"method": args.method, "max_rounds": args.max_rounds})
    result = calibrate_mission(mission, options, progress=_say(args))
    paths = result.write(args.out)
    if "report" not in paths:
        from swathflow.calibration.report import write_report
        paths["report"] = write_report(result, os.path.join(args.out, "report.html"))
    for line in result.summary_lines():
        _echo(args, line)
    _echo(args, f"wrote {', '.join(paths[k] for k in paths if k != 'report')} and "
          f"{paths['report']}")
    return 0


def rectify(args) -> int:
    """``swathflow rectify MISSION [--calibration FILE] --out DIR``: one COG per image,
    each ``swathflow.to_cog(swathflow.rectify(...))`` (through ``rectify_mission``)."""
    from swathflow.collector import uncollected
    with uncollected():
        from swathflow.rectification.mission import rectify_mission
    products = tuple(p.strip() for p in (args.products or "").split(",") if p.strip())
    if not args.calibration and not getattr(args, "quiet", False):
        print("swathflow rectify: warning: no --calibration given: rectifying with the "
              "mission's prior parameters (uncalibrated; metres off where the priors are "
              "wrong); run 'swathflow calibrate' and pass its calibration.json",
              file=sys.stderr)
    rectify_mission(args.mission, args.out, calibration=args.calibration,
                    images=_ids(args.images), method=args.method, kernel=args.kernel,
                    tol=args.tolerance, tile=args.tile, products=products,
                    progress=_say(args),
                    bands=args.bands or None, dtype=args.dtype, mask_band=args.mask_band,
                    compress=args.compress, workers=getattr(args, "workers", None),
                    dask_address=getattr(args, "dask_address", None))
    return 0


def _flow_run():
    """The flow's ``run``."""
    from swathflow.flows.mission import run
    return run


def mosaic(args) -> int:
    """``swathflow mosaic SOURCE --out FILE.tif``: match strips, feather, write a COG
    (``swathflow.mosaicking.api.write_mosaic``: the code of ``swathflow.mosaic(..., out)``
    and of the flow's mosaic task, without building the lazy array)."""
    from swathflow.cluster import dask_client
    from swathflow.mosaicking.api import write_mosaic as run
    from swathflow.mosaicking.mosaic import find_inputs, mission_strips
    out = os.fspath(args.out)
    # absolute: the overlaps may be matched by worker processes elsewhere
    paths = [os.path.abspath(p) for p in find_inputs(args.source)
             if os.path.abspath(p) != os.path.abspath(out)]
    mission = args.mission
    if mission is None and os.path.isfile(os.path.join(os.fspath(args.source), "mission.toml")):
        mission = args.source
    strips = mission_strips(mission) if mission else None
    anchors, control = _mosaic_anchor(args.anchor, mission, args.calibration)
    log = _say(args)
    workers = args.workers
    # the overlap matching's compiled search releases the GIL: threads in this process by
    # default (a local cluster of processes cost 2x the CPU); a cluster only when named
    cluster = not args.no_match and bool(args.dask_address)
    with (dask_client(args.dask_address, n_workers=workers) if cluster
          else contextlib.nullcontext()):
        rep = run(paths, out, per_image=args.per_image, anchors=anchors, control=control,
                  feather=args.feather, mode="cut" if args.no_feather else "feather",
                  balance=not args.no_balance, match=not args.no_match,
                  max_shift=args.max_shift, tile=args.tile, workers=workers, strips=strips,
                  log=log)
    if log:
        from swathflow.mosaicking.report import node_line
        for nd in rep.get("nodes", []):
            log("  " + node_line(nd, (rep.get("grid") or {}).get("res")))
        log(f"wrote {out} ({rep['shape'][0]} x {rep['shape'][1]} px, {rep['seconds']:.1f} s, "
            f"{rep['mpx_per_s']} Mpx/s), {os.path.splitext(out)[0]}.png and "
            f"{os.path.splitext(out)[0]}.json")
    return 0


def _mosaic_anchor(anchor, mission, calibration):
    """(anchors, control) of ``swathflow mosaic``: ``--anchor gcp`` reads the mission's
    control points and measures each image's absolute offset with the calibration."""
    anchor = list(anchor or ())
    if "gcp" not in anchor:
        return anchor, None
    if not mission or not calibration:
        raise SwathflowError("--anchor gcp needs the mission (--mission, or a mission folder "
                             "as SOURCE) and the calibration the swings were rectified with "
                             "(--calibration)")
    from swathflow.tasks.stages import mosaic_control
    control = mosaic_control(os.fspath(mission), os.fspath(calibration))
    if not control:
        raise SwathflowError(f"{mission}: --anchor gcp needs control points (role control "
                             f"in the GCP file); the mission has none")
    return [a for a in anchor if a != "gcp"], control


def _print_summary(result: dict, args=None) -> None:
    if getattr(args, "quiet", False):
        return
    print(f"mission {result['mission']}: done")
    print(f"  calibration  {result['calibration']}")
    if result.get("report"):
        print(f"  report       {result['report']}")
    print(f"  rectified    {len(result['rectified'])} swings in "
          f"{os.path.dirname(result['rectified'][0]) if result['rectified'] else '-'}")
    print(f"  mosaic       {result['mosaic']}")
    if result.get("catalog"):
        print(f"  catalogue    {result['catalog']}")
    print("  stage timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in result["timings"].items()))


def run(args) -> int:
    """``swathflow run MISSION --out DIR``: the whole flow."""
    from swathflow.flows.fresh import fresh_result
    done = fresh_result(args.mission, args.out, args.calibration)   # no Prefect, no Dask
    if done is not None:
        _echo(args, f"mission {done['mission']}: up to date, nothing to recompute "
              f"(products in {os.path.abspath(args.out)})")
        return 0
    _checked(args.mission, args.calibration)
    run_flow = _flow_run()
    from swathflow.flows.services import interrupt_quickly
    with interrupt_quickly():
        result = run_flow(args.mission, args.out, args.calibration, args.dask_address,
                          args.cluster, args.jobs)
    _print_summary(result, args)
    return 0


def _checked(mission, calibration) -> None:
    """The first steps of ``swathflow run``: what an earlier run killed by SIGKILL left
    serving ended and this run's processes marked
    (:func:`~swathflow.flows.services.end_orphans`); Prefect's temporary server started on a
    thread (:func:`~swathflow.flows.services.start_prefect`); the inputs checked meanwhile
    (bad input is told here, before the Dask cluster starts; Prefect stops its server as
    the process exits)."""
    _own_processes()
    from swathflow.flows.services import start_prefect
    start_prefect()
    from swathflow.collector import uncollected
    with uncollected(freeze=False):
        from swathflow.flows.guard import check_run_inputs
        check_run_inputs(mission, calibration)


def _own_processes() -> None:
    """End what earlier runs killed by SIGKILL left serving; mark this run's children."""
    from swathflow.flows.services import end_orphans, mark_run
    end_orphans()
    mark_run()


def _first_run_notice(args) -> None:
    """Say so when numba's cache is empty (a new install or clone): the kernels are
    compiled for this machine during the run, once."""
    from swathflow.kernelcache import cached
    from swathflow.rectification.paint import paint_window    # every run calls it
    if not cached(paint_window):
        _echo(args, "first run of this install: numba compiles swathflow's kernels for this "
              "machine as they are first called (about a minute more, once; later runs "
              "load them from its cache)", file=sys.stderr)


#: what ``swathflow demo`` writes into its folder (and the output lock): the folder may be
#: marked ignored by git only when it holds nothing else
DEMO_ENTRIES = frozenset({"mission", "products", ".gitignore", ".swathflow.lock"})


def ignored_by_git(folder: Path) -> None:
    """Mark the demo's folder ignored by git (a ``.gitignore`` of ``*``, as pytest marks its
    cache), so that a demo run inside a clone leaves ``git status`` clean. A folder holding
    anything the demo does not write (a person's own folder given as ``--out``) is left
    alone."""
    folder.mkdir(parents=True, exist_ok=True)
    if {p.name for p in folder.iterdir()} <= DEMO_ENTRIES and not (folder / ".gitignore").exists():
        from swathflow.io import write_text
        write_text(folder / ".gitignore", "# written by 'swathflow demo': ignore this folder\n*\n")


def demo_products(result: dict) -> list[tuple[str, str]]:
    """(what, path) of the products a person opens first after the demo, those that exist:
    the mosaic's HTML report and quicklook, then the calibration report."""
    found = []
    mosaic = result.get("mosaic")
    if mosaic:
        stem = os.path.splitext(os.path.abspath(mosaic))[0]
        found += [("mosaic report", stem + ".html"), ("mosaic quicklook", stem + ".png")]
    if result.get("report"):
        found.append(("calibration report", os.path.abspath(result["report"])))
    return [(what, path) for what, path in found if os.path.exists(path)]


def demo_summary(result: dict, seconds: float) -> str:
    """The demo's closing lines: its time and the products to open first, with paths."""
    lines = [f"demo finished in {seconds:.0f} s; open these first:"]
    lines += [f"  {what:<19} {path}" for what, path in demo_products(result)]
    return "\n".join(lines)


def demo(args) -> int:
    """``swathflow demo``: simulate the demo mission, then run the whole flow on it."""
    _own_processes()
    from swathflow.flows.services import start_prefect
    start_prefect()     # Prefect's temporary server starts while the mission is simulated
    out = Path(args.out).resolve()
    ignored_by_git(out)
    run_flow = _flow_run()
    from swathflow.simulation import simulate as simulate_mission
    mission = out / "mission"
    t0 = time.perf_counter()
    _first_run_notice(args)
    if not (mission / "mission.toml").exists():
        _echo(args, f"simulating the {args.preset} mission into {mission} ...",
              file=sys.stderr)
        simulate_mission(mission, preset=args.preset, seed=0)
    result = run_flow(mission, out / "products")
    _print_summary(result, args)
    _echo(args, demo_summary(result, time.perf_counter() - t0))
    return 0
