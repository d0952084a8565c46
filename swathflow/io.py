"""Atomic output: write to a temporary file beside the target, then rename."""
from __future__ import annotations

import contextlib
import os
import tempfile


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None, exclusive: bool = False):
    """Yield a temporary path in the target's folder; rename it onto ``path`` on success
    (with ``exclusive``: link it there, never over a file that exists by then, which
    raises FileExistsError, and remove the temporary name).

    On any exception the temporary file is removed and ``path`` keeps its old content.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    base = os.path.basename(path)
    _clear_stale(folder, base)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.{os.getpid()}.",
                               suffix=suffix or ".tmp" + os.path.splitext(base)[1], dir=folder)
    os.close(fd)
    try:
        yield tmp
        if os.path.exists(tmp):   # mkstemp makes 0600 files: give the usual umask'd mode
            os.chmod(tmp, 0o666 & ~_umask())
        if exclusive:
            os.link(tmp, path)
            os.remove(tmp)
        else:
            os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def scratch_path(target, kind: str):
    """A temporary file beside ``target``, named ``.<target name>.<pid>.<kind>`` (so a
    killed run's leftovers are cleared by the next :func:`atomic_path` of the target),
    removed afterwards."""
    folder, base = os.path.split(os.path.abspath(os.fspath(target)))
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.{os.getpid()}.", suffix=f".{kind}", dir=folder)
    os.close(fd)
    try:
        yield tmp
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)


def _clear_stale(folder: str, base: str) -> None:
    """Remove temporaries of ``base`` left by a process that no longer runs (a run killed
    by SIGKILL or a power cut): their names carry the writer's process id."""
    prefix = f".{base}."
    try:
        names = [n for n in os.listdir(folder) if n.startswith(prefix)]
    except OSError:
        return
    for n in names:
        pid = n[len(prefix):].split(".", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            with contextlib.suppress(OSError):
                os.remove(os.path.join(folder, n))


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:         # exists, owned by someone else
        return True
    return True


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()   # read once: os.umask is process-wide and racy in threads


def _umask() -> int:
    return _UMASK


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def png_bytes(img, level: int | None = None) -> bytes:
    """PNG file bytes (Pillow) of an 8-bit image: ``(rows, cols)`` grey, or
    ``(2, rows, cols)`` grey + alpha. ``level`` None: zlib's run-length strategy (the
    mosaic's 1024-px quicklook in 28 against 54 ms at level 3, 4 % larger; level 3 was
    four times faster than the default 6 and about 1 % larger); else that zlib level."""
    import io

    import numpy as np
    from PIL import Image
    a = np.asarray(img, np.uint8)
    im = (Image.fromarray(np.ascontiguousarray(a), "L") if a.ndim == 2 else
          Image.fromarray(np.ascontiguousarray(np.moveaxis(a, 0, -1)), "LA"))
    buf = io.BytesIO()
    if level is None:
        im.save(buf, "PNG", compress_level=3, compress_type=3)     # 3: Z_RLE
    else:
        im.save(buf, "PNG", compress_level=level)
    return buf.getvalue()
