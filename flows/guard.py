"""Command-line safeguards: outputs checked before any work, SIGTERM handled like Ctrl-C,
operating-system failures (disk full, permissions) told in one line.
"""
from __future__ import annotations

import contextlib
import errno
import os
import signal
import tempfile

from swathflow.errors import SwathflowError

#: commands whose --out is a folder / a file
OUT_FOLDER = ("calibrate", "rectify", "run", "demo")
OUT_FILE = ("mosaic",)


class Terminated(BaseException):
    """SIGTERM arrived: unwind like KeyboardInterrupt (outputs are atomic, temporaries
    removed, the ephemeral Prefect server and Dask cluster shut down on the way out)."""


def signalled(exc: BaseException) -> BaseException | None:
    """The :class:`Terminated` or :class:`KeyboardInterrupt` behind ``exc`` (None: none).
    A signal handler can raise inside Python code that compiled code called (numba's
    dispatcher unpickling a function's globals, a ctypes callback): that code then
    reports a ``SystemError`` whose cause is the signal's exception."""
    for e in _chain(exc):
        if isinstance(e, (Terminated, KeyboardInterrupt)):
            return e
    return None


#: SIGTERM arrived during :func:`on_sigterm` (its exception may have been swallowed: a
#: signal handler that raises inside a ``__del__`` or a callback of compiled code is only
#: printed as "Exception ignored"): the command then still ends as terminated
SIGTERM_RECEIVED: list = []


@contextlib.contextmanager
def on_sigterm():
    def handler(signum, frame):
        SIGTERM_RECEIVED.append(True)
        raise Terminated()
    SIGTERM_RECEIVED.clear()
    try:
        old = signal.signal(signal.SIGTERM, handler)
    except ValueError:          # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _writable_folder(folder: str, what: str) -> None:
    folder = os.path.abspath(folder)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise SwathflowError(f"{folder}: {what} exists and is not a folder; give a folder "
                             f"name (or remove the file)")
    probe = folder
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        raise SwathflowError(f"{folder}: cannot create {what}: {probe} is a file")
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise SwathflowError(f"{folder}: cannot write {what} there ({exc.strerror}); give "
                             f"a folder you can write to") from None


def check_outputs(args) -> None:
    """The --out of a command must be writable, of the right kind, and never on or over an
    input: no input file of the command (the mission.toml, every file it names, the
    calibration, the reference) may be the output file or lie in the output folder."""
    out = getattr(args, "out", None)
    if out is None:
        return
    _plain_path(out)
    if args.command == "simulate":     # its --texture and --dem must not be in OUT
        _not_over_inputs(args, out, folder=True)
    elif args.command in OUT_FOLDER:
        _writable_folder(out, "the output folder")
        _not_inside_inputs(args, out)
        _not_over_inputs(args, out, folder=True)
        if args.command == "run":
            _no_other_mission(args, out)
    elif args.command in OUT_FILE:
        if os.path.isdir(out):
            raise SwathflowError(f"{out}: --out is a folder; give a file name such as "
                                 f"{os.path.join(out, 'mosaic.tif')}")
        _writable_folder(os.path.dirname(os.path.abspath(out)), "the output folder")
        _not_an_input(args, out)
        _not_over_inputs(args, out, folder=False)


def _plain_path(out) -> None:
    """An output path with ``#`` or ``?``: the STAC writer (URLs) and GDAL (``/vsi`` and
    URL syntax) read those characters as a URL's fragment or query, so a product could be
    written to another file (``/x/victim.txt#2`` -> ``/x/victim.txt``): refused."""
    bad = [ch for ch in "#?" if ch in os.fspath(out)]
    if bad:
        raise SwathflowError(f"{out}: --out holds {' and '.join(repr(b) for b in bad)}, "
                             f"which the STAC and GDAL writers read as part of a URL (the "
                             f"products could land in another file): give a path without "
                             f"them")


#: the sidecar files written beside a mosaic ``NAME.tif``
MOSAIC_SIDECARS = (".png", ".report.png", ".json", ".html")


def mission_inputs(mission) -> list[str]:
    """The files a mission's commands read: its mission.toml, every existing file its
    string values name (any depth, also outside the folder), and the files beside each
    that share its name (an ENVI image's header)."""
    from swathflow.ingest.tomlfile import load, named_paths
    root = os.path.abspath(os.fspath(mission))
    if os.path.isfile(root):
        root = os.path.dirname(root)
    toml = os.path.join(root, "mission.toml")
    found = {toml} if os.path.isfile(toml) else set()
    try:
        cfg = load(toml)
    except (OSError, ValueError):
        return sorted(found)
    for path in named_paths(cfg, root):
        p = os.fspath(path)
        try:
            if os.path.isfile(p):
                found.add(p)
                found.update(_namesakes(p))
        except (OSError, ValueError):
            continue
    return sorted(found)


def _namesakes(path: str) -> list[str]:
    """Files beside ``path`` with the same name before the extension (ENVI .img/.hdr)."""
    folder, name = os.path.split(path)
    stem = os.path.splitext(name)[0]
    try:
        return [os.path.join(folder, f) for f in os.listdir(folder)
                if os.path.splitext(f)[0] == stem]
    except OSError:
        return []


def command_inputs(args) -> list[str]:
    """Every input file of a command (see :func:`mission_inputs`), its --calibration,
    --reference and --reference-dem, and for ``mosaic`` its --mission's files (or those of
    a mission folder given as SOURCE)."""
    files: list[str] = []
    mission = getattr(args, "mission", None)
    if args.command == "mosaic":
        src = os.fspath(getattr(args, "source", "") or "")
        if mission is None and os.path.isfile(os.path.join(src, "mission.toml")):
            mission = src
    if mission:
        files += mission_inputs(mission)
    for key in ("calibration", "reference", "reference_dem", "texture", "dem"):
        v = getattr(args, key, None)
        if v:
            files.append(os.fspath(v))
    return files


def _not_over_inputs(args, out, folder: bool) -> None:
    real = os.path.realpath(out)
    targets = {real}
    if not folder:
        base = os.path.splitext(real)[0]
        targets.update(base + s for s in MOSAIC_SIDECARS)
    for p in command_inputs(args):
        rp = os.path.realpath(p)
        if folder and _written_beside(args, real, rp, p):
            continue
        if folder and (rp == real or rp.startswith(real.rstrip(os.sep) + os.sep)):
            raise SwathflowError(f"{out}: the output folder holds an input of the command "
                                 f"({p}); its products could be written over it: give an "
                                 f"output folder that holds none of the command's inputs")
        if not folder and rp in targets:
            raise SwathflowError(f"{out}: the mosaic (or its .png/.json sidecar) would be "
                                 f"written over an input of the command ({p}): give another "
                                 f"file name")


#: where ``rectify`` and ``run --calibration`` write in their output folder (relative
#: paths; a folder ends with "/"): a calibration file elsewhere in it stays untouched
PRODUCT_PLACES = {"rectify": ("rectify.json", ".tif"),
                  "run": ("pos/", "rectified/", "stac/", "mosaic.", "run.swathflow.json")}


def _written_beside(args, out_real: str, real: str, given: str) -> bool:
    """True for the --calibration file of ``rectify`` or ``run`` lying in the output folder
    where the command writes nothing (``calibrate M --out O`` then ``rectify M
    --calibration O/calibration.json --out O`` is the usual way): it is read, never
    written over. Every other input inside the output folder is refused."""
    cal = getattr(args, "calibration", None)
    places = PRODUCT_PLACES.get(args.command)
    if not cal or places is None or os.fspath(cal) != os.fspath(given):
        return False
    relpath = os.path.relpath(real, out_real)
    if relpath.startswith(".."):
        return False
    return not any(relpath.startswith(pl) if pl.endswith(("/", ".")) else
                   relpath == pl or relpath.endswith(pl) for pl in places)


def _no_other_mission(args, out) -> None:
    """``run --out`` holding the rectified swings of another mission: the run would keep
    them beside its own, and a later ``swathflow mosaic`` of the folder blend both."""
    from swathflow.ingest.tomlfile import load
    folder = os.path.join(out, "rectified")
    if not os.path.isdir(folder):
        return
    try:
        cfg = load(os.path.join(args.mission, "mission.toml"))
    except (OSError, ValueError):
        return              # the command itself reports the mission
    mission = cfg.get("mission") if isinstance(cfg.get("mission"), dict) else {}
    name = str(mission.get("name", os.path.basename(os.path.abspath(args.mission))))
    ids = {str(e.get("id")) for e in cfg.get("images", []) if isinstance(e, dict)}
    others = []
    for f in sorted(os.listdir(folder)):
        if f.startswith(".") or not f.lower().endswith((".tif", ".tiff")):
            continue
        tags = _tags(os.path.join(folder, f))
        if tags is None or "image_id" not in tags:
            continue
        if tags.get("mission", name) != name or tags["image_id"] not in ids:
            others.append(f"{f} (mission {tags.get('mission', '?')!r}, image "
                          f"{tags['image_id']!r})")
    if others:
        raise SwathflowError(f"{out}: holds rectified swings that are not this mission's "
                             f"images ({', '.join(others[:3])}"
                             f"{' ...' if len(others) > 3 else ''}); they would stay beside "
                             f"this mission's and be mosaicked with them: give an empty "
                             f"output folder (or this mission's own)")


def _tags(path: str) -> dict | None:
    import rasterio
    try:
        with rasterio.open(path) as src:
            return src.tags()
    except (rasterio.errors.RasterioError, OSError):
        return None


def _not_an_input(args, out: str) -> None:
    """mosaic --out must not name one of the swings it reads."""
    from swathflow.mosaicking.mosaic import find_inputs as _find_inputs
    target = os.path.realpath(out)
    try:
        inputs = _find_inputs(args.source)
    except SwathflowError:
        return              # the command itself reports a bad source
    for p in inputs:
        if os.path.realpath(p) == target and _is_swing(p):
            raise SwathflowError(f"{out}: --out is one of the input swings; writing the "
                                 f"mosaic there would destroy it: give another file name")


def _is_swing(path: str) -> bool:
    """A rectified swing (tagged with its image id), not an earlier mosaic."""
    tags = _tags(path)
    return tags is None or "image_id" in tags       # unreadable: never write over it


def _not_inside_inputs(args, out: str) -> None:
    mission = getattr(args, "mission", None)
    if mission and os.path.realpath(out) == os.path.realpath(mission):
        raise SwathflowError(f"{out}: --out is the mission folder itself; give a separate "
                             f"output folder")


@contextlib.contextmanager
def output_lock(args):
    """Hold a lock on the command's output (folder, or mosaic file) for the whole run; a
    second run on the same --out stops at once and names the process holding it. The
    lock (flock) goes with its process, even one killed by SIGKILL."""
    import fcntl
    out = getattr(args, "out", None)
    if out is None or args.command not in OUT_FOLDER + OUT_FILE:
        yield
        return
    if args.command in OUT_FILE:
        folder, name = os.path.split(os.path.abspath(out))
        lock = os.path.join(folder, f".{name}.lock")
    else:
        folder = os.path.abspath(out)
        lock = os.path.join(folder, ".swathflow.lock")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise SwathflowError(f"{out}: another swathflow run (process {pid}) is writing "
                                 f"there; wait for it to finish, or give another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)


def _chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def _free_bytes(path) -> float:
    import shutil
    p = os.path.abspath(path)
    while p and not os.path.exists(p):
        p = os.path.dirname(p)
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return float("inf")


def explain_os_error(exc: BaseException, out=None) -> str | None:
    """One line for a disk-full, permission or write failure (None: not such a failure).
    ``out``: the command's output path, whose free space tells a full disk apart."""
    try:
        from rasterio.errors import RasterioError
    except ImportError:         # pragma: no cover
        RasterioError = ()  # noqa: N806
    chain = list(_chain(exc))
    texts = " | ".join(str(e) for e in chain)
    full = any(isinstance(e, OSError) and e.errno == errno.ENOSPC for e in chain) or (
        "No space left on device" in texts or "Free disk space" in texts)
    raster_write = isinstance(exc, RasterioError) and "write" in texts.lower()
    if full or (raster_write and out is not None and _free_bytes(out) < 2**20):
        where = getattr(exc, "filename", None) or out or ""
        return (f"the disk is full{' writing ' + str(where) if where else ''}: free some "
                f"space and re-run (finished outputs are kept, temporaries removed)")
    if isinstance(exc, PermissionError):
        return f"permission denied: {exc.filename or exc}: choose a path you can write to"
    if raster_write:
        return (f"cannot write a raster: {texts.splitlines()[0][:200]}: check the output "
                f"folder (space, permissions) and re-run")
    return None


def band_problems(parts: dict) -> list:
    """``[rectify] bands`` of a mission that does not fit one of its images (the
    ``validate`` command's check: the selection's syntax and wavelengths are the
    rectification's, :func:`swathflow.rectification.mission.mission_bands`)."""
    from types import SimpleNamespace

    from swathflow.errors import FormatError
    from swathflow.ingest.problems import Problem
    cfg, images = parts.get("config") or {}, parts.get("images") or {}
    if not isinstance(cfg.get("rectify"), dict) or not images:
        return []
    from swathflow.rectification.mission import mission_bands
    m = SimpleNamespace(config=cfg, path=parts["root"], images=images)
    toml = str(parts["root"] / "mission.toml")
    for iid in images:
        try:
            mission_bands(m, iid)
        except (FormatError, OSError, ValueError) as exc:
            return [Problem(toml, "[rectify].bands", str(exc).split("mission.toml: ", 1)[-1],
                            "select bands the images have: 1-based numbers, ranges "
                            "(\"1,4-6\") or wavelengths (\"550nm\")")]
    return []


def check_run_inputs(mission, calibration=None):
    """``swathflow run``'s inputs, checked before Prefect or Dask start: the mission (every
    problem listed at once) and the calibration file (readable, for the mission's
    sensor). Returns the loaded mission, memoised for the flow's stages (which would
    otherwise load and check it again)."""
    from swathflow.ingest.mission import load_mission
    from swathflow.tasks.swings import remember
    m = load_mission(mission)
    remember(mission, m)
    if calibration:
        from swathflow.formats.calibfile import read_calibration
        doc = read_calibration(calibration)
        if doc.get("sensor") not in (None, m.sensor.get("model")):
            raise SwathflowError(f"{calibration}: calibration is for sensor "
                                 f"{doc['sensor']!r}, the mission uses "
                                 f"{m.sensor.get('model')!r}: pass the calibration of "
                                 f"this mission's sensor")
    return m
