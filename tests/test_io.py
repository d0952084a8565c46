"""Atomic writes: nothing half-written, the old content kept on failure, usual permissions."""
import os
import stat
from pathlib import Path

import pytest

from swathflow.io import atomic_path, write_text


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "out.txt"
    write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_exclusive_write_never_replaces_a_file_made_meanwhile(tmp_path):
    """``exclusive``: the new file is linked into place; a file that appeared at the target
    while it was written is kept, the write fails, and no temporary is left."""
    target = tmp_path / "db"
    with atomic_path(target, exclusive=True) as tmp:
        Path(tmp).write_text("ours")
    assert target.read_text() == "ours" and os.listdir(tmp_path) == ["db"]
    other = tmp_path / "other"
    with pytest.raises(FileExistsError):
        with atomic_path(other, exclusive=True) as tmp:
            Path(tmp).write_text("ours")
            other.write_text("theirs")          # made by another process meanwhile
    assert other.read_text() == "theirs"
    assert sorted(os.listdir(tmp_path)) == ["db", "other"]


def test_written_files_get_the_umask_mode(tmp_path):
    """Not mkstemp's private 0600: the mode any plain open() would give."""
    write_text(tmp_path / "a.txt", "x")
    with open(tmp_path / "b.txt", "w") as f:
        f.write("x")
    mode = stat.S_IMODE((tmp_path / "a.txt").stat().st_mode)
    assert mode == stat.S_IMODE((tmp_path / "b.txt").stat().st_mode)
    assert mode & 0o044, "others cannot read the output"


@pytest.mark.parametrize("level", [None, 1, 6])
def test_png_bytes_lossless_at_every_setting(level):
    """The fast run-length default and the zlib levels give the same pixels back."""
    import io

    import numpy as np
    from PIL import Image

    from swathflow.io import png_bytes
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 256, (2, 37, 53), dtype=np.uint8)
    grey[1, :5] = 0
    back = np.asarray(Image.open(io.BytesIO(png_bytes(grey, level))))
    assert np.array_equal(np.moveaxis(back, -1, 0), grey)
    flat = grey[0]
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png_bytes(flat, level)))), flat)
