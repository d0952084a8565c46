"""``[mission] date``: the flight's UTC date places the POS and line times (GPS seconds of
week) on the calendar; ``validate`` checks it against the POS, and the mission gives each
image's acquisition span from it (the STAC items' times)."""
import datetime as dt
import re
import shutil

import pytest

from swathflow.ingest.mission import load_mission, validate_mission


def _with_date(tiny_mission, tmp_path, line: str | None):
    m = tmp_path / "m"
    shutil.copytree(tiny_mission, m)
    toml = (m / "mission.toml").read_text()
    toml = re.sub(r"(?m)^date = .*\n", "", toml)
    if line is not None:
        toml = toml.replace("[mission]\n", f"[mission]\n{line}\n", 1)
    (m / "mission.toml").write_text(toml)
    return m


def _date_problems(path):
    return [str(p) for p in validate_mission(path) if "[mission].date" in str(p)]


def test_the_simulated_flight_date_holds_its_pos_and_gives_the_spans(tiny_mission, tmp_path):
    from swathflow.formats.gpstime import gps_seconds_of_week_to_utc
    m = load_mission(_with_date(tiny_mission, tmp_path, "date = 2024-06-05"))
    assert not _date_problems(m.path)
    assert m.date == dt.date(2024, 6, 5)
    for iid in m.image_ids:
        t = m.lines(iid)["time"]
        start, end = m.acquisition_span(iid)
        # the simulator flies from Wednesday 12:00 GPS (302400 s of week): 18 leap seconds
        assert start == dt.datetime(2024, 6, 5, 11, 59, 42, tzinfo=dt.UTC) + \
            dt.timedelta(seconds=float(t.min()) - 302400.0)
        assert end - start == dt.timedelta(seconds=float(t.max() - t.min()))
        assert start == gps_seconds_of_week_to_utc(float(t.min()), m.date)


@pytest.mark.parametrize("line, words", [
    ("date = 2024-06-04", "Wednesday"),            # the POS is on Wednesday, not Tuesday
    ('date = "5 June 2024"', "UTC date"),
    ("date = 20240605", "UTC date"),
])
def test_a_wrong_flight_date_is_reported(tiny_mission, tmp_path, line, words):
    found = _date_problems(_with_date(tiny_mission, tmp_path, line))
    assert len(found) == 1 and words in found[0], found


def test_no_date_no_span(tiny_mission, tmp_path):
    m = load_mission(_with_date(tiny_mission, tmp_path, None))
    assert m.date is None and m.acquisition_span(m.image_ids[0]) is None
    assert not [p for p in validate_mission(m.path) if "date" in str(p)]
