"""Fuzzing every reader (issue 13): whatever the bytes, a reader returns or raises a
SwathflowError naming the file; validation lists problems, never "unexpected content"
(an internal exception), never a hang. Bounded examples keep the default run fast."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from swathflow.errors import SwathflowError

FAST = settings(max_examples=25, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

# CSV-ish text: header-like words, numbers, separators, junk
_cell = st.one_of(st.sampled_from(["time", "lat", "lon", "h", "roll", "pitch", "heading",
                                   "line", "swing", "pitch_comp", "gcp_id", "image_id",
                                   "element", "x", "y", "z", "role", "control", "check",
                                   "L1", "R1", "nan", "inf", "-1e308", "", '"', "é"]),
                  st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.integers(-10**6, 10**6).map(str), st.text(max_size=6))
_row = st.lists(_cell, max_size=9).map(",".join)
csv_text = st.lists(_row, max_size=12).map("\n".join)


def _reads(fn, path):
    try:
        fn(path)
    except SwathflowError:
        pass


@FAST
@given(data=st.binary(max_size=136 * 4))
def test_sbet_reader(tmp_path, data):
    from swathflow.formats.pos import read_sbet
    p = tmp_path / "pos.sbet"
    p.write_bytes(data)
    _reads(read_sbet, p)


@FAST
@given(rec=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=17 * 3,
                    max_size=17 * 3))
def test_sbet_reader_whole_records(tmp_path, rec):
    from swathflow.formats.pos import read_sbet
    p = tmp_path / "pos.sbet"
    np.asarray(rec, "<f8").tofile(p)
    _reads(read_sbet, p)


@FAST
@given(text=csv_text)
def test_pos_csv_reader(tmp_path, text):
    from swathflow.formats.pos import read_pos_csv
    p = tmp_path / "pos.csv"
    p.write_text("time,lat,lon,h,roll,pitch,heading\n" + text, encoding="utf-8")
    _reads(read_pos_csv, p)


@FAST
@given(text=st.text(max_size=300))
def test_calibration_json_reader(tmp_path, text):
    from swathflow.formats.calibfile import read_calibration
    p = tmp_path / "calibration.json"
    p.write_text(text, encoding="utf-8")
    _reads(read_calibration, p)


_json = st.recursive(st.one_of(st.none(), st.booleans(), st.floats(), st.integers(),
                               st.text(max_size=5)),
                     lambda ch: st.lists(ch, max_size=4) | st.dictionaries(
                         st.sampled_from(["format", "sensor", "parameters", "value",
                                          "sigma", "u_gps"]), ch, max_size=4), max_leaves=12)


@FAST
@given(doc=st.fixed_dictionaries({"format": st.just("swathflow-calibration/1"),
                                  "parameters": _json}))
def test_calibration_json_structures(tmp_path, doc):
    import json

    from swathflow.formats.calibfile import calibration_priors, read_calibration
    p = tmp_path / "calibration.json"
    p.write_text(json.dumps(doc), encoding="utf-8")
    try:
        calibration_priors(read_calibration(p))
    except SwathflowError:
        pass


# ------------------------------------------------------------------------------------------
# files read through validation

@pytest.fixture(scope="module")
def mission(tmp_path_factory) -> Path:
    from swathflow.flows.cli import main
    out = tmp_path_factory.mktemp("fuzz") / "m"
    assert main(["simulate", str(out), "--preset", "tiny", "--geometry-only",
                 "--image-format", "envi"]) == 0
    return out


def _validate_with(mission: Path, rel: str, content: bytes | str):
    from swathflow.ingest.mission import validate_mission
    p = mission / rel
    keep = p.read_bytes()
    try:
        p.write_bytes(content.encode("utf-8") if isinstance(content, str) else content)
        probs = validate_mission(mission)
    finally:
        p.write_bytes(keep)
    bad = [str(pr) for pr in probs if "unexpected content" in str(pr)]
    assert not bad, bad
    return probs


@FAST
@given(text=csv_text)
def test_lines_csv_through_validation(mission, text):
    _validate_with(mission, "images/L1.lines.csv", "line,time,swing,pitch_comp\n" + text)


@FAST
@given(text=csv_text)
def test_gcp_csv_through_validation(mission, text):
    _validate_with(mission, "gcp.csv", "gcp_id,image_id,line,element,x,y,z,role\n" + text)


_toml_value = st.one_of(st.integers(-10**12, 10**12), st.floats(), st.booleans(),
                        st.text(max_size=8), st.lists(st.integers(), max_size=3))


@FAST
@given(table=st.sampled_from(["mission", "sensor", "pos", "terrain", "gcp", "calibration"]),
       key=st.sampled_from(["name", "crs", "gsd", "model", "n_elements", "focal_length",
                            "k0", "file", "format", "max_gap", "dem", "height", "vertical",
                            "u_gps", "max_pixels", "pixel_pitch", "undulation"]),
       value=_toml_value)
def test_mission_toml_values_through_validation(mission, table, key, value):
    import tomllib
    toml = (mission / "mission.toml").read_text()
    cfg = tomllib.loads(toml)
    cfg.setdefault(table, {})[key] = value
    _validate_with(mission, "mission.toml", _dump_toml(cfg))


@FAST
@given(text=st.text(max_size=200))
def test_mission_toml_text_through_validation(mission, text):
    _validate_with(mission, "mission.toml", text)


@FAST
@given(lines=st.lists(st.sampled_from([
    "ENVI", "samples = 64", "samples = -3", "samples = 1e9", "lines = 699", "lines = 0",
    "bands = 1", "bands = 3", "data type = 4", "data type = 99", "data type = 12",
    "interleave = bsq", "interleave = bil", "interleave = xyz", "byte order = 0",
    "byte order = 1", "header offset = 100000", "header offset = -5", "{", "}", "= ="]),
    max_size=10))
def test_envi_header_through_validation(mission, lines):
    hdr = next((mission / "images").glob("L1*.hdr"))
    _validate_with(mission, f"images/{hdr.name}", "\n".join(lines) + "\n")


_band_list = st.lists(st.sampled_from(["400", "500.5", "nan", "x", "", "1e9"]), max_size=5)


@FAST
@given(bands=st.sampled_from([1, 2, 3]), wl=_band_list, fw=_band_list,
       extra=st.sampled_from([0, 1, 64]))
def test_envi_header_valid_means_rectify_reads_it(mission, bands, wl, fw, extra):
    """Issue 44: "OK" from validate means rectify reads the image: an ENVI header whose band
    lists (wavelength, FWHM) or band count do not fit, or whose data file holds more
    bytes than it says, is a problem of validate, not a later refusal."""
    from swathflow.ingest.mission import validate_mission
    from swathflow.rectification.rawimage import open_raw_image
    hdr = next((mission / "images").glob("L1*.hdr"))
    data = next(p for p in (mission / "images").glob("L1*")
                if p.suffix not in (".hdr", ".csv"))
    keep_h, keep_d = hdr.read_bytes(), data.read_bytes()
    try:
        text = keep_h.decode().replace("bands = 1", f"bands = {bands}")
        text += (f"wavelength = {{{', '.join(wl)}}}\n" if wl else "")
        text += (f"fwhm = {{{', '.join(fw)}}}\n" if fw else "")
        hdr.write_text(text)
        data.write_bytes(keep_d * bands + b"\0" * extra)
        probs = validate_mission(mission)
        errors = [p for p in probs if p.level == "error"]
        assert not [p for p in probs if "unexpected content" in str(p)]
        if not errors:
            img = open_raw_image(data)
            assert len(img.bands) == bands
            assert extra == 0           # a data file longer than its header is refused
    finally:
        hdr.write_bytes(keep_h)
        data.write_bytes(keep_d)


_prior = st.fixed_dictionaries({"value": st.lists(st.floats(), min_size=3, max_size=3)},
                                optional={"sigma": st.one_of(
                                    st.lists(st.floats(), min_size=3, max_size=3),
                                    st.floats())})


@FAST
@given(block=st.sampled_from(["opk_sen", "u_gps", "opk_pos_L"]), prior=_prior,
       bands=st.sampled_from([None, "1", "2", "1-3", "550nm", "", "0", [1], [5]]))
def test_mission_table_valid_means_the_commands_accept_it(mission, block, prior, bands):
    """Issue 44: a [calibration] prior or a [rectify] bands that validate passes is one the
    calibration and rectification accept: finite values, sigmas finite and >= 0 (0: held
    at the value), bands that fit the image."""
    import math
    import tomllib

    from swathflow.flows.guard import band_problems
    from swathflow.ingest.mission import inspect_mission, load_mission
    from swathflow.rectification.mission import mission_bands
    cfg = tomllib.loads((mission / "mission.toml").read_text())
    cfg["calibration"][block] = prior
    if bands is not None:
        cfg["rectify"] = {"bands": bands}
    p = mission / "mission.toml"
    keep = p.read_bytes()
    try:
        p.write_text(_dump_toml(cfg))
        probs, parts = inspect_mission(mission)         # what 'swathflow validate' checks
        assert not [x for x in probs if "unexpected content" in str(x)]
        if not [x for x in probs if x.level == "error"]:
            probs = band_problems(parts)
        if not [x for x in probs if x.level == "error"]:
            m = load_mission(mission)
            b = m.priors.block(block)
            assert all(math.isfinite(v) for v in b.value)
            if "sigma" in prior:
                assert all(math.isfinite(s) and s >= 0 for s in b.sigma)
            assert all(f for f, s in zip(b.fixed, b.sigma) if s == 0)
            for iid in m.image_ids:
                mission_bands(m, iid)
    finally:
        p.write_bytes(keep)


def _dump_toml(cfg: dict) -> str:
    """A small TOML writer for the fuzzed configurations (tables, arrays of tables)."""
    import json

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(v), repr(v))
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{json.dumps(k)} = {val(x)}" for k, x in v.items()) + " }"
        if isinstance(v, str):
            return json.dumps(v)
        return str(v)

    out = []
    for k, v in cfg.items():
        if isinstance(v, dict):
            out.append(f"[{k}]")
            out += [f"{json.dumps(kk)} = {val(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for x in v:
                out.append(f"[[{k}]]")
                out += [f"{json.dumps(kk)} = {val(vv)}" for kk, vv in x.items()]
        else:
            out.insert(0, f"{json.dumps(k)} = {val(v)}")
    return "\n".join(out) + "\n"


def test_fuzz_mission_unchanged_is_valid(mission):
    """The fixture itself is a valid mission (the fuzzed cases start from a good one)."""
    from swathflow.ingest.mission import validate_mission
    assert [p for p in validate_mission(mission) if p.level == "error"] == []
    shutil.rmtree(mission / "truth", ignore_errors=True)
