"""Issue 44, silently wrong re-runs: a stage's cache trusts an output only when it is whole
(its size and sha256 recorded when written) and its inputs by content, never by size and
modification time alone."""
from __future__ import annotations

import os

from swathflow.cache import is_fresh, mark_done, stage_key


def _same_stamp_rewrite(path, data: bytes) -> None:
    """Rewrite ``path`` with ``data`` (same size) and put its modification time back."""
    st = os.stat(path)
    assert len(data) == st.st_size
    path.write_bytes(data)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_mtime_ns == st.st_mtime_ns


def test_stage_key_sees_content_changed_with_size_and_mtime_kept(tmp_path):
    f = tmp_path / "pos.csv"
    f.write_bytes(b"time,lat\n1,10.0\n")
    k1 = stage_key("pos", [f])
    _same_stamp_rewrite(f, b"time,lat\n1,11.0\n")
    assert stage_key("pos", [f]) != k1


def test_truncated_output_is_not_trusted(tmp_path):
    out = tmp_path / "L1.tif"
    out.write_bytes(b"x" * 4096)
    mark_done(out, "k")
    assert is_fresh(out, "k")
    out.write_bytes(b"x" * 1000)            # a copy or a disk that cut it short
    assert not is_fresh(out, "k")


def test_corrupted_output_of_the_same_size_is_not_trusted(tmp_path):
    out = tmp_path / "L1.tif"
    out.write_bytes(b"x" * 4096)
    mark_done(out, "k")
    _same_stamp_rewrite(out, b"x" * 2048 + b"y" + b"x" * 2047)
    assert not is_fresh(out, "k")


def test_manifest_of_an_older_version_without_checksum_is_not_trusted(tmp_path):
    out = tmp_path / "L1.tif"
    out.write_bytes(b"x" * 16)
    (tmp_path / "L1.tif.swathflow.json").write_text('{"key": "k"}')
    assert not is_fresh(out, "k")


def test_run_is_not_up_to_date_after_an_input_changed_with_its_stamp_kept(tmp_path):
    """``run`` said "up to date, nothing to recompute" after an input's content changed
    with its size and mtime kept."""
    from swathflow.flows.fresh import fresh_result, record
    m = tmp_path / "m"
    m.mkdir()
    (m / "mission.toml").write_text('[pos]\nfile = "pos.csv"\n')
    (m / "pos.csv").write_bytes(b"time,lat\n1,10.0\n")
    out = tmp_path / "o"
    out.mkdir()
    (out / "mosaic.tif").write_bytes(b"m")
    record(m, out, None, {"mission": str(m)})
    assert fresh_result(m, out) is not None
    _same_stamp_rewrite(m / "pos.csv", b"time,lat\n1,11.0\n")
    assert fresh_result(m, out) is None


def test_a_folder_output_is_trusted_only_while_every_file_is_whole(tmp_path):
    """A stage whose output is a folder (the STAC catalogue): a file of it cut short or
    removed makes it stale."""
    out = tmp_path / "stac"
    (out / "L1").mkdir(parents=True)
    (out / "catalog.json").write_text('{"id": "c"}')
    (out / "L1" / "L1.json").write_text('{"id": "L1"}')
    mark_done(out, "k")
    assert is_fresh(out, "k")
    (out / "L1" / "L1.json").write_text('{"id"')
    assert not is_fresh(out, "k")
    mark_done(out, "k")
    (out / "L1" / "L1.json").unlink()
    assert not is_fresh(out, "k")
