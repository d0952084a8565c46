"""The ``swathflow`` command line. Each subcommand lazily imports what it needs, so
``swathflow --help`` and ``swathflow sensors`` stay fast (no Prefect import).

Bad input never ends in a traceback: :class:`~swathflow.errors.SwathflowError` is printed
as one clear message with exit code 2.
"""
from __future__ import annotations

import argparse
import sys
from importlib import import_module

from swathflow.flows.cli.argtypes import (MAX_SHIFT, TILE, finite_float, int_between,
                                         positive_float, positive_int)


def _sensors(args) -> int:
    from swathflow.sensormodel import list_sensors
    from swathflow.sensormodel.registry import _registry
    reg = _registry()
    if not reg:
        print("no sensor models registered")
        return 1
    width = max(len(n) for n in reg)
    for name, (cls, target) in reg.items():
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        print(f"{name:<{width}}  {cls.kind or '-':<12} {target}\n{'':<{width}}  {doc}")
        for label, text in _hooks(cls):
            print(f"{'':<{width}}  {label:<12} {text}")
    return 0 if list_sensors() else 1


def _hooks(cls) -> list[tuple[str, str]]:
    """What a sensor plugin brings besides its geometry (a broken hook is reported, never
    raised: the listing must show every plugin)."""
    out = [("line table", "line, " + ", ".join(cls.line_columns))]
    if cls.directions:
        out.append(("directions", ", ".join(cls.directions)))
    try:
        strategy = cls.calibration_strategy()
        doc = (type(strategy).__doc__ or "").strip().splitlines() if strategy else []
        out.append(("calibration", (doc[0] if doc else type(strategy).__name__) if strategy
                    else "control points (the generic adjustment)"))
        sim = cls.simulator()
        if sim is not None:
            out.append(("presets", ", ".join(getattr(sim, "PRESETS", ())) or "-"))
    except Exception as exc:  # noqa: BLE001 - a broken plugin must never break the listing
        out.append(("broken hook", f"{type(exc).__name__}: {exc}"))
    return out


def _call(target: str):
    """A handler that imports ``module:function`` only when the subcommand runs."""
    def run(args) -> int:
        module, _, func = target.partition(":")
        return int(getattr(import_module(module), func)(args) or 0)
    return run


def _verbosity_parser() -> argparse.ArgumentParser:
    """--quiet / --verbose, shared by every command."""
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors (no progress bars, no summary)")
    g.add_argument("-v", "--verbose", action="store_true",
                   help="also print each stage as plain lines when stderr is not a terminal, "
                        "and Prefect's and Dask's informational logs")
    return common


#: the warning filter (``PYTHONWARNINGS``) that quiets the resource tracker's leak report
TRACKER_QUIET = "ignore::UserWarning:multiprocessing.resource_tracker"


def _apply_verbosity(args) -> None:
    import logging
    import os

    from swathflow.flows.progress import QUIET, VERBOSE, NORMAL, set_verbosity
    quiet, verbose = getattr(args, "quiet", False), getattr(args, "verbose", False)
    set_verbosity(QUIET if quiet else VERBOSE if verbose else NORMAL)
    if verbose:     # before Prefect is imported by the command
        os.environ["PREFECT_LOGGING_LEVEL"] = "INFO"
        os.environ["DASK_LOGGING__DISTRIBUTED"] = "info"
        logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    else:
        # this process's terminal shows swathflow's own lines (a failure is told once, by
        # the command): Prefect's console handler quiet (its documented logging override
        # variables); the flow run's logs still reach Prefect's API and are stored
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "CRITICAL")
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
        # Prefect's internal services too (its "debug" handler: after Ctrl-C, whose SIGINT
        # also stops Prefect's temporary server, its event and log workers reported every
        # call that no longer reached it)
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_DEBUG_LEVEL", "CRITICAL")
        if args.command == "run":
            # ... and its API log handler wrote "--- Error logging to API ---" straight to
            # stderr: what the standard library's logging.raiseExceptions = False, its
            # documented setting for production use, leaves out
            logging.raiseExceptions = False
        # a run killed by SIGKILL: Python's multiprocessing resource tracker (a child,
        # on the same terminal) frees the semaphores of Dask's nannies and says so in a
        # two-line UserWarning after the shell's prompt is back; it inherits the
        # warning filters of the environment (Python's documented PYTHONWARNINGS)
        given = os.environ.get("PYTHONWARNINGS", "")
        if TRACKER_QUIET not in given.split(","):
            os.environ["PYTHONWARNINGS"] = ",".join(filter(None, (given, TRACKER_QUIET)))
    # Prefect's client telemetry (and the notice it prints on a first interactive run): off
    # for the command line unless the environment says otherwise; importing swathflow's
    # modules from Python changes no setting
    os.environ.setdefault("DO_NOT_TRACK", "1")
    # a first run in a new Prefect home: Prefect's temporary server builds its database
    # (25-45 s on 2 busy cores) before it answers; Prefect's default wait is 20 s
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="swathflow",
        description="Calibrate, orthorectify and mosaic airborne line-scanner imagery.",
        epilog="Start with 'swathflow demo'. Each command has its own --help.")
    from swathflow._version import __version__
    p.add_argument("--version", action="version", version=f"swathflow {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    common = [_verbosity_parser()]

    s = sub.add_parser("sensors", parents=common, help="list the registered sensor models (plugins)")
    s.set_defaults(func=_sensors)

    s = sub.add_parser("validate", parents=common, help="check a mission folder and list every problem")
    s.add_argument("mission", help="mission folder (with mission.toml)")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:validate"))

    s = sub.add_parser("simulate", parents=common, help="write a simulated mission bundle with its truth")
    s.add_argument("out", help="output mission folder")
    s.add_argument("--preset", default="tiny",
                   help="a preset of a registered sensor's simulator (listed by "
                        "'swathflow sensors'; default tiny)")
    s.add_argument("--seed", type=int_between(0, 2**32 - 1), default=0,
                   help="random seed, 0 to 2^32-1 (default 0)")
    s.add_argument("--texture", help="orthophoto GeoTIFF/JPEG+world file for the ground truth")
    s.add_argument("--dem", help="DEM GeoTIFF for the terrain shape")
    s.add_argument("--geometry-only", action="store_true",
                   help="write blank images (line tables, POS, GCPs, truth only): fast")
    s.add_argument("--render", action="store_true",
                   help="render images and the truth ortho even where the preset does not "
                        "(paper: slow)")
    s.add_argument("--no-direction-effect", action="store_true",
                   help="same true IMU boresight for left and right swings")
    s.add_argument("--direction-omega", type=finite_float, metavar="DEG",
                   help="true omega_L - omega_R (deg; default: the paper's Table 4)")
    s.add_argument("--gcp-noise", type=finite_float, metavar="PX",
                   help="GCP image measurement noise, px per axis (default 1)")
    s.add_argument("--gross-errors", type=finite_float, dest="gross_fraction", metavar="FRACTION",
                   help="fraction of GCP measurements with a 10-40 px gross error")
    s.add_argument("--image-format", choices=("tif", "envi"), help="raw image format")
    s.add_argument("--pos-format", choices=("sbet", "csv"), help="POS file format")
    s.add_argument("--force", action="store_true",
                   help="write into OUT even when it already holds a mission or files")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:simulate"))

    s = sub.add_parser("calibrate", parents=common,
                       help="estimate calibration parameters from control points or a "
                            "reference orthophoto")
    s.add_argument("mission")
    s.add_argument("--out", required=True, help="output folder (calibration.json, report.html)")
    s.add_argument("--model", choices=["15", "12"], default="15",
                   help="15: separate IMU boresight for left and right swings (default); "
                        "12: one shared boresight")
    s.add_argument("--fix", action="append", metavar="NAME",
                   help="hold a parameter at its prior (block such as opk_sen, or opk_sen[2]); "
                        "repeatable")
    s.add_argument("--images", help="comma-separated images whose control points enter the "
                                    "adjustment (default: all); the others are validated")
    s.add_argument("--drift", action="store_true",
                   help="estimate a time-linear drift of the per-direction boresight angles")
    s.add_argument("--no-robust", action="store_true",
                   help="no blunder detection (robust reweighting and data snooping)")
    s.add_argument("--no-vce", action="store_true",
                   help="keep the a-priori weights (no variance component estimation)")
    s.add_argument("--vce-priors", action="store_true",
                   help="also estimate one variance component for the priors")
    s.add_argument("--sigma-px", type=positive_float, default=1.0,
                   help="a-priori sigma of image coordinates in pixels (default 1)")
    s.add_argument("--method", choices=("joint", "two-step", "both"), default="joint",
                   help="for calibration strategies with tie points and orientation fixes: "
                        "joint adjustment (default), the iterative two-step scheme, or "
                        "both (compared in the report)")
    s.add_argument("--max-rounds", type=positive_int, default=50,
                   help="two-step scheme: stop after this many rounds even when it is not "
                        "yet within 0.1 sigma of the joint optimum (default 50)")
    s.add_argument("--reference", metavar="ORTHO",
                   help="reference orthophoto (north-up raster with a CRS): automatic control "
                        "points matched against it replace gcp.csv (default: the mission's "
                        "[reference] when it has no gcp.csv)")
    s.add_argument("--reference-dem", metavar="DEM",
                   help="heights of the reference's points (default: the mission's terrain)")
    s.add_argument("--ties", action="store_true",
                   help="with a reference: also match overlapping swings of opposite "
                        "directions with each other (tie points, ground unknown)")
    s.add_argument("--rounds", type=int_between(1, 100), default=4,
                   help="with a reference: at most this many match / adjust rounds (default 4)")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:calibrate"))

    s = sub.add_parser("rectify", parents=common, help="orthorectify every swing to a COG")
    s.add_argument("mission")
    s.add_argument("--calibration", help="calibration.json to use (default: mission priors)")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--method", choices=("exact", "polynomial"), default="exact",
                   help="exact (default: inverse mapping through the sensor model, gap-free) "
                        "or polynomial (the paper's fast forward method)")
    s.add_argument("--kernel", choices=("nearest", "bilinear", "cubic"), default="bilinear",
                   help="resampling kernel (default bilinear)")
    s.add_argument("--products", default="",
                   help="extra products, comma separated: glt (output->raw lookup), "
                        "igm (ground coordinates of every raw pixel)")
    s.add_argument("--images", help="only these image ids, comma separated")
    s.add_argument("--tolerance", type=positive_float, default=0.05,
                   help="bound on the interpolated raw coordinates' error, pixels (default 0.05)")
    s.add_argument("--tile", type=TILE, default=512,
                   help="output tile size, a multiple of 16 from 16 to 4096 (default 512)")
    s.add_argument("--bands", default="",
                   help="bands to rectify (default all), comma separated: 1-based indices "
                        "and ranges (1,4-6) or wavelengths with a unit (550nm,0.67um: the "
                        "nearest band, from the ENVI header or GDAL band metadata)")
    s.add_argument("--dtype", choices=("uint8", "uint16", "int16", "uint32", "int32",
                                       "float32", "float64"),
                   help="output data type (default: the raw image's; float64 raw -> "
                        "float32). Integer nodata: the raw image's nodata value, else the "
                        "type's lowest (0 unsigned); a valid value equal to it moves one "
                        "unit. Float output: NaN")
    s.add_argument("--mask-band", action="store_true",
                   help="integer output: no nodata value, an internal mask band instead "
                        "(every value of the type stays data)")
    s.add_argument("--compress", choices=("deflate", "zstd"), default="deflate",
                   help="COG compression (default deflate, which every GDAL and TIFF reader "
                        "opens); zstd compresses about 1.6x faster, but needs GDAL 2.3 or "
                        "later built with ZSTD (rasterio's wheels and the usual GDAL builds)")
    s.add_argument("--workers", type=positive_int,
                   help="local Dask worker processes (default: one per core, at most one "
                        "per image)")
    s.add_argument("--dask-address",
                   help="rectify on an existing Dask scheduler (default: a local cluster)")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:rectify"))

    s = sub.add_parser("mosaic", parents=common,
                       help="match strips and blend rectified swings into a mosaic")
    s.add_argument("source", help="mission folder or folder of rectified swings")
    s.add_argument("--out", required=True, help="output mosaic GeoTIFF")
    s.add_argument("--mission", help="mission folder or mission.toml giving each image's strip")
    s.add_argument("--anchor", action="append", metavar="ID",
                   help="image id or strip number held fixed (repeatable), or 'gcp': tie the "
                        "network to the mission's control points (needs --mission and "
                        "--calibration; absolute offsets with sigmas in the JSON report). "
                        "Default: the mean offset of each connected group is zero")
    s.add_argument("--calibration", help="calibration.json the swings were rectified with "
                                         "(for --anchor gcp)")
    s.add_argument("--per-image", action="store_true",
                   help="one offset per image instead of one per strip")
    s.add_argument("--feather", type=positive_int, default=64,
                   help="feathering distance cap in pixels (default 64)")
    s.add_argument("--no-feather", action="store_true", help="hard seams (nearest footprint)")
    s.add_argument("--no-balance", action="store_true", help="no radiometric balancing")
    s.add_argument("--no-match", action="store_true", help="no offset estimation")
    s.add_argument("--max-shift", type=MAX_SHIFT, default=12,
                   help="largest offset searched, pixels, 1 to 256 (default 12)")
    s.add_argument("--tile", type=TILE, default=1024,
                   help="tile size in pixels, a multiple of 16 from 16 to 4096 (default 1024)")
    s.add_argument("--workers", type=positive_int,
                   help="threads for the overlap matching and the rendering (default: "
                        "all cores)")
    s.add_argument("--dask-address",
                   help="match the overlaps on an existing Dask scheduler (default: threads "
                        "in this process)")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:mosaic"))

    s = sub.add_parser("run", parents=common, help="run the whole mission flow (Prefect, Dask)")
    s.add_argument("mission")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--calibration", help="use this calibration.json instead of calibrating")
    s.add_argument("--dask-address", help="an existing Dask scheduler (default: local cluster)")
    s.add_argument("--cluster", choices=("local", "slurm"), default="local",
                   help="where the Dask workers run without --dask-address: local processes "
                        "(default) or SLURM jobs through dask-jobqueue (settings: Dask's "
                        "jobqueue.slurm config, see deploy/dask/jobqueue.yaml)")
    s.add_argument("--jobs", type=positive_int, default=2,
                   help="--cluster slurm: number of worker jobs to submit (default 2)")
    s.set_defaults(func=_call("swathflow.flows.cli.commands:run"))

    s = sub.add_parser("demo", parents=common,
                       help="simulate the demo mission and run the whole flow on it")
    s.add_argument("--out", default="swathflow-demo", help="output folder (default ./swathflow-demo)")
    s.add_argument("--preset", default="demo", help=argparse.SUPPRESS)
    s.set_defaults(func=_call("swathflow.flows.cli.commands:demo"))
    return p


#: commands whose process, once the command has returned, ends without the interpreter's
#: teardown (see :func:`_leave`): every output is closed and in place by then
QUICK_EXIT = ("rectify",)

#: the exit code of the program's command, for :func:`_leave` (None: not returned)
_CODE: list = [None]


def main(argv: list[str] | None = None) -> int:
    import gc
    program = argv is None       # the swathflow program itself (not a call from Python)
    if program:
        _one_blas_thread()
        gc.disable()             # start-up: imports, parsing (see _main)
        import atexit
        atexit.register(_leave)  # first registered: runs after every other exit handler
    try:
        code = _main(argv, program)
    finally:
        if program:      # the program ends here: leave its objects to the process's end
            gc.freeze()  # rather than to the collector's last passes over every module
    return code          # (0.3-0.5 CPU-s after a rectification)


def _one_blas_thread() -> None:
    """OpenBLAS on one thread, unless the environment says otherwise, when numpy is not
    imported yet (it reads the setting once): the program's parallelism is its own worker
    processes and threads, one per core (Dask's nannies set the same for their workers).
    numpy's and scipy's OpenBLAS each start a thread at import that spins about 0.1 CPU-s
    before it sleeps, and spin again after each matrix product, on the core the other
    work needs: one thread measured 0.19 of the rectify command's 3.5 CPU-s on the demo,
    2.20 -> 1.89 CPU-s for ``swathflow mosaic`` of the 48-swing benchmark and
    3.90 -> 3.63 for ``swathflow calibrate`` of the demo."""
    import os
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _leave() -> None:
    """The program's last exit handler: after a command of :data:`QUICK_EXIT` returned,
    end the process here, once every other exit handler has run (Python runs them last
    registered first) and stdout and stderr are flushed, without the interpreter's teardown
    of its 1,600 modules (0.08-0.09 CPU-s, 0.1-0.2 s of wall after a rectification).
    Any other command, or an exception, takes the usual way out."""
    if _CODE[0] is None:
        return
    import logging
    import os
    logging.shutdown()
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (OSError, ValueError):     # a closed pipe or stream: nothing more to say
            pass
    os._exit(_CODE[0])


def _main(argv: list[str] | None, program: bool = False) -> int:
    import gc
    import warnings

    from swathflow.errors import SwathflowError
    # raw scanner images carry no geotransform by nature: rasterio's warning about it is
    # noise here (catch_warnings around each open is not thread-safe under Dask threads)
    warnings.filterwarnings("ignore", message="Dataset has no geotransform")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    _apply_verbosity(args)
    from swathflow.flows.guard import (
        SIGTERM_RECEIVED,
        Terminated,
        check_outputs,
        explain_os_error,
        on_sigterm,
        output_lock,
        signalled,
    )
    _show_warnings(args.command, quiet=getattr(args, "quiet", False))
    if program:          # the start-up's objects (modules) live to the end: out of the
        gc.freeze()      # collector's passes (0.05-0.1 CPU-s), then the collector on for
        gc.enable()      # the command's own work
    try:
        with on_sigterm():
            check_outputs(args)
            with output_lock(args):
                code = int(args.func(args) or 0)
        if SIGTERM_RECEIVED:                 # its exception was swallowed on the way
            raise Terminated()
    except SwathflowError as exc:
        print(f"swathflow {args.command}: error: {exc}", file=sys.stderr)
        code = 2
    except (Terminated, KeyboardInterrupt) as exc:
        code = _signalled(args.command, exc)
    except BrokenPipeError:
        code = _pipe_closed()
    except Exception as exc:
        # the signal's exception raised inside compiled code's call, or swallowed before
        if signalled(exc) is not None or SIGTERM_RECEIVED:
            code = _signalled(args.command, signalled(exc) or Terminated())
        else:
            msg = explain_os_error(exc, getattr(args, "out", None))
            if msg is None:
                raise
            print(f"swathflow {args.command}: error: {msg}", file=sys.stderr)
            code = 2
    if program and args.command in QUICK_EXIT:
        _CODE[0] = code
    if program and args.command == "run" and code in (130, 143):     # interrupted
        from swathflow.flows.services import leave_if_prefect_stopped
        leave_if_prefect_stopped(code)
    return code


def _pipe_closed() -> int:
    """The reader of our output went away (``swathflow sensors | head -1``, a killed
    parent): end quietly, the way command-line tools do (exit 141, 128 + SIGPIPE), with
    stdout pointed at /dev/null so that the interpreter's last flush raises nothing."""
    import os
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return 141


def _signalled(command: str, exc: BaseException) -> int:
    """The message and exit code of a run ended by SIGTERM (143) or Ctrl-C (130)."""
    from swathflow.flows.guard import Terminated
    if isinstance(exc, Terminated):
        print(f"swathflow {command}: terminated (SIGTERM); finished outputs are kept, "
              f"re-run to complete", file=sys.stderr)
        return 143
    print(f"swathflow {command}: interrupted; finished outputs are kept, "
          f"re-run to complete", file=sys.stderr)
    return 130


def _show_warnings(command: str, quiet: bool = False) -> None:
    """swathflow's own warnings (mission, sensor plugins) as one plain line each, with one
    ``swathflow <command>: warning:`` prefix (their texts carry none); with ``-q`` no
    warning at all."""
    import warnings

    # the base class, not the modules that raise them: importing those (pandas, xarray,
    # dask) before every command cost about 0.3 CPU-s
    from swathflow.errors import SwathflowWarning
    # the one before any command's (main called again in one process: not a chain)
    previous = getattr(warnings.showwarning, "before_swathflow", warnings.showwarning)

    def show(message, category, filename, lineno, file=None, line=None):
        if quiet:               # -q: nothing but errors, a library's warnings neither
            return
        if issubclass(category, SwathflowWarning):
            print(f"swathflow {command}: warning: {message}", file=sys.stderr)
        else:
            previous(message, category, filename, lineno, file, line)
    show.before_swathflow = previous
    warnings.showwarning = show


if __name__ == "__main__":
    sys.exit(main())
