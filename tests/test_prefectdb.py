"""A new Prefect home's database: a copy of the migrated empty one kept per Prefect version
(flows/prefectdb.py), checked against Prefect's own migrations (their head revision, read
by alembic from Prefect's migration scripts) and by a real server serving on it."""
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import prefect.server.database as database
from alembic.script import ScriptDirectory

from swathflow.flows import prefectdb


def _head() -> str:
    base = Path(database.__file__).parent / "_migrations"
    heads = ScriptDirectory(str(base), version_locations=[str(base / "versions" / "sqlite")]
                            ).get_heads()
    assert len(heads) == 1
    return heads[0]


def _revision(path) -> str:
    with sqlite3.connect(path) as db:
        return db.execute("select version_num from alembic_version").fetchone()[0]


def test_new_home_gets_a_database_migrated_to_prefects_head(tmp_path, monkeypatch):
    from prefect.settings import (PREFECT_HOME, PREFECT_SERVER_DATABASE_CONNECTION_URL,
                                  temporary_settings)
    monkeypatch.setenv("SWATHFLOW_CACHE", str(tmp_path / "cache"))
    # the database's default place in the home (a test server's harness may have named
    # another database for the session)
    with temporary_settings({PREFECT_HOME: tmp_path / "home"},
                            restore_defaults={PREFECT_SERVER_DATABASE_CONNECTION_URL}):
        _new_home(tmp_path)


def _new_home(tmp_path):
    # an interrupted build and an interrupted copy, by a process that has ended
    (tmp_path / "cache").mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    template = prefectdb.template_path()
    left = [template.with_name(f".{template.name}.{dead}.tmp"),
            template.with_name(f".{template.name}.{dead}.tmp-wal")]
    for f in left:
        f.write_bytes(b"half")
    ours = template.with_name(f".{template.name}.{os.getppid()}.tmp")   # a live one: kept
    ours.write_bytes(b"")
    path = prefectdb.database_path()
    assert path == tmp_path / "home" / "prefect.db"
    assert prefectdb.seed() is True
    assert _revision(path) == _revision(template) == _head()
    assert prefectdb.at_head() is True       # the server's migration on start: left out
    assert not any(f.exists() for f in left) and ours.exists()
    assert sorted(p.name for p in (tmp_path / "home").iterdir()) == ["prefect.db"]
    # a database that exists is never replaced, the template is reused as it is
    path.write_bytes(b"the user's runs")
    stamp = template.stat().st_mtime_ns
    assert prefectdb.seed() is False and path.read_bytes() == b"the user's runs"
    assert prefectdb.at_head() is False      # not a database: Prefect's migration runs
    other = tmp_path / "other" / "prefect.db"
    assert prefectdb.seed(other) is True and template.stat().st_mtime_ns == stamp
    assert other.read_bytes() == template.read_bytes()


def test_template_named_by_prefects_version_and_migrations(tmp_path, monkeypatch):
    import prefect
    monkeypatch.setenv("SWATHFLOW_CACHE", str(tmp_path))
    name = prefectdb.template_path().name
    monkeypatch.setattr(prefect, "__version__", "0.0.0")
    assert prefectdb.template_path().name != name
    assert prefectdb.template_path().parent == tmp_path


def test_not_sqlite_or_unwritable_is_left_to_prefect(tmp_path, monkeypatch):
    from prefect.settings import PREFECT_SERVER_DATABASE_CONNECTION_URL, temporary_settings
    for url in ("postgresql+asyncpg://u:p@127.0.0.1:1/prefect", "sqlite+aiosqlite:///:memory:"):
        with temporary_settings({PREFECT_SERVER_DATABASE_CONNECTION_URL: url}):
            assert prefectdb.database_path() is None and prefectdb.seed() is False
    monkeypatch.setenv("SWATHFLOW_CACHE", "/proc/no-such-folder")
    assert prefectdb.seed(tmp_path / "home" / "prefect.db") is False
    assert not (tmp_path / "home" / "prefect.db").exists()


def test_database_behind_the_template_is_migrated(tmp_path, monkeypatch):
    """Only a database at the template's revision skips the migration on start: one at
    another revision, one without alembic's table, a missing one and a missing template
    are left to Prefect's migration."""
    import sqlite3
    monkeypatch.setenv("SWATHFLOW_CACHE", str(tmp_path / "cache"))
    template = prefectdb.template_path()
    template.parent.mkdir()

    def db(path, *revisions):
        with sqlite3.connect(path) as c:
            c.execute("create table if not exists t (x)")
            if revisions:
                c.execute("create table alembic_version (version_num varchar(32))")
                c.executemany("insert into alembic_version values (?)",
                              [(r,) for r in revisions])
        return path
    user = db(tmp_path / "user.db", "aaa")
    assert prefectdb.at_head(user) is False                  # no template yet
    db(template, "bbb")
    assert prefectdb.revisions(template) == {"bbb"}
    assert prefectdb.at_head(user) is False                  # behind (or ahead)
    assert prefectdb.at_head(db(tmp_path / "head.db", "bbb")) is True
    assert prefectdb.at_head(db(tmp_path / "two.db", "bbb", "ccc")) is False
    assert prefectdb.at_head(db(tmp_path / "none.db")) is False
    assert prefectdb.at_head(tmp_path / "missing.db") is False
    assert not (tmp_path / "missing.db").exists()
