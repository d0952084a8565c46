"""GPS time on a flight date: POS and line times are GPS seconds of week (SBET and most
POS processors); the mission states the flight's UTC date (``[mission] date``), which
fixes the week. GPS time runs ahead of UTC by the leap seconds since 1980-01-06.

>>> import datetime as dt
>>> gps_seconds_of_week_to_utc(302400.0, dt.date(2024, 6, 5))   # Wednesday 12:00 GPS
datetime.datetime(2024, 6, 5, 11, 59, 42, tzinfo=datetime.timezone.utc)
"""
from __future__ import annotations

import datetime as dt

WEEK = 604800.0
DAY = 86400.0
GPS_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.UTC)

#: (first UTC day of the offset, GPS - UTC in seconds): IERS Bulletin C; none announced
#: after 2017-01-01 up to this release
LEAP_SECONDS = ((dt.date(1981, 7, 1), 1), (dt.date(1982, 7, 1), 2), (dt.date(1983, 7, 1), 3),
                (dt.date(1985, 7, 1), 4), (dt.date(1988, 1, 1), 5), (dt.date(1990, 1, 1), 6),
                (dt.date(1991, 1, 1), 7), (dt.date(1992, 7, 1), 8), (dt.date(1993, 7, 1), 9),
                (dt.date(1994, 7, 1), 10), (dt.date(1996, 1, 1), 11),
                (dt.date(1997, 7, 1), 12), (dt.date(1999, 1, 1), 13),
                (dt.date(2006, 1, 1), 14), (dt.date(2009, 1, 1), 15),
                (dt.date(2012, 7, 1), 16), (dt.date(2015, 7, 1), 17),
                (dt.date(2017, 1, 1), 18))


def leap_seconds(day: dt.date) -> int:
    """GPS - UTC (seconds) on the UTC date ``day``."""
    offset = 0
    for start, value in LEAP_SECONDS:
        if day >= start:
            offset = value
    return offset


def week_start(day: dt.date) -> dt.datetime:
    """Sunday 00:00 (GPS time, as a UTC-labelled datetime) of the GPS week holding ``day``."""
    sunday = day - dt.timedelta(days=(day.weekday() + 1) % 7)
    return dt.datetime(sunday.year, sunday.month, sunday.day, tzinfo=dt.UTC)


def gps_seconds_of_week_to_utc(seconds: float, day: dt.date) -> dt.datetime:
    """The UTC time of ``seconds`` GPS seconds of the week holding the UTC date ``day``."""
    gps = week_start(day) + dt.timedelta(seconds=float(seconds))
    return gps - dt.timedelta(seconds=leap_seconds(day))


def flight_date(value) -> dt.date | None:
    """``[mission] date`` as a date: a TOML date (or date-time) or an ISO string; None for
    None. Raises ValueError for anything else."""
    if value is None or (isinstance(value, dt.date) and not isinstance(value, dt.datetime)):
        return value
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, str):
        return dt.date.fromisoformat(value.strip())
    raise ValueError(f"not a date: {value!r}")


def date_mismatch(seconds: float, day: dt.date) -> str | None:
    """Why the flight date ``day`` cannot be the UTC date of the epoch ``seconds`` (GPS
    seconds of week), or None when it is."""
    if not (0.0 <= seconds < WEEK):
        return (f"{seconds:g} s is not a GPS second of week (0 to {WEEK:.0f}): the POS and "
                "line times must be GPS seconds of week to be placed on the date")
    got = gps_seconds_of_week_to_utc(seconds, day).date()
    if got != day:
        return (f"the first epoch, {seconds:.3f} GPS seconds of week, is on "
                f"{got:%A} {got.isoformat()} UTC in the week of {day.isoformat()} "
                f"(a {day:%A}), not on {day.isoformat()}")
    return None
