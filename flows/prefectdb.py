"""A new Prefect home's database, copied from a migrated empty one kept per Prefect version.

Prefect's server migrates a new SQLite database through all its revisions (114 in Prefect
3.8) when it first starts: 25-45 s wall on a 2-core machine, paid by the first run in every
new ``PREFECT_HOME`` (a fresh machine, a CI job, a container, a test's own home). The first
migration is kept as a template in swathflow's cache folder
(``$SWATHFLOW_CACHE``, else ``$XDG_CACHE_HOME/swathflow``, else ``~/.cache/swathflow``),
named by Prefect's version and its migrations; a database that does not exist yet is a copy
of it, and the server's own migration on start then finds nothing to do.

Both files are written atomically (:func:`swathflow.io.atomic_path`: a temporary name, then
a rename, or a link for the database), so an interrupted build leaves no template, and a
database that exists is never replaced.
Only SQLite databases are concerned (PostgreSQL is left to Prefect). Imports Prefect's
server code: called by the process that serves (:mod:`swathflow.flows.standby`).
"""
from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

from swathflow.io import atomic_path

_SQLITE = "sqlite+aiosqlite:///"


def cache_folder() -> Path:
    """swathflow's cache folder for this user (not created here)."""
    if os.environ.get("SWATHFLOW_CACHE"):
        return Path(os.environ["SWATHFLOW_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "swathflow"


def database_path() -> Path | None:
    """The SQLite file of the current Prefect settings' database (None: not SQLite, or
    in memory)."""
    from prefect.settings import get_current_settings
    url = get_current_settings().server.database.connection_url
    url = url.get_secret_value() if hasattr(url, "get_secret_value") else str(url)
    if not url.startswith(_SQLITE) or ":memory:" in url or "mode=memory" in url:
        return None
    return Path(url[len(_SQLITE):].split("?", 1)[0])


def template_path() -> Path:
    """Where this Prefect's migrated empty database is kept: named by Prefect's version and
    the names of its SQLite migrations."""
    import prefect
    import prefect.server.database as database
    versions = Path(database.__file__).parent / "_migrations" / "versions" / "sqlite"
    names = sorted(p.name for p in versions.glob("*.py"))
    key = hashlib.sha256("\n".join([prefect.__version__, *names]).encode()).hexdigest()[:16]
    return cache_folder() / f"prefect-{prefect.__version__}-{key}.db"


def seed(path: Path | None = None) -> bool:
    """Make the database at ``path`` (default: the current settings' SQLite database) a
    copy of the template when it does not exist yet, building the template first when
    there is none. True when it copied; False when the database exists, is not SQLite, or
    the template cannot be made (the server then migrates as usual)."""
    import shutil
    path = Path(path) if path is not None else database_path()
    if path is None or path.exists():
        return False
    try:
        template = template_path()
        if not template.exists():
            _build(template)
        with atomic_path(path, exclusive=True) as tmp:   # never over one made meanwhile
            shutil.copyfile(template, tmp)
    except Exception:  # noqa: BLE001 - any failure: the server migrates as it would have
        return False
    return True


def revisions(path) -> frozenset[str]:
    """The alembic revisions a SQLite database says it is at (empty: none, or not
    readable), read without writing to it."""
    import sqlite3
    try:
        uri = Path(path).resolve().as_uri() + "?mode=ro&immutable=1"   # no -wal, -shm made
        with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=1)) as db:
            return frozenset(r[0] for r in db.execute("select version_num from alembic_version"))
    except (sqlite3.Error, OSError, ValueError):
        return frozenset()


def at_head(path: Path | None = None) -> bool:
    """Whether the database at ``path`` (default: the current settings' SQLite database)
    is at the revision of this Prefect's migrated template (:func:`template_path`, made
    by Prefect's own migration): then the server's migration on start has nothing to do
    but load alembic and its 114 revisions (0.3-0.6 s of the server's start). False
    when either is missing or unreadable, or not SQLite: Prefect migrates as usual."""
    path = Path(path) if path is not None else database_path()
    if path is None or not path.exists():
        return False
    template = template_path()
    head = revisions(template) if template.exists() else frozenset()
    return bool(head) and revisions(path) == head


def _build(template: Path) -> None:
    """Migrate a new database at a temporary name beside ``template`` (Prefect's own
    migration, in this process), then rename it to ``template``."""
    import asyncio

    from prefect.server.database import provide_database_interface
    from prefect.server.database.dependencies import temporary_database_interface
    from prefect.settings import PREFECT_SERVER_DATABASE_CONNECTION_URL, temporary_settings

    async def migrate():
        db = provide_database_interface()
        await db.create_db()
        await (await db.engine()).dispose()    # closes its connections: the log is checkpointed

    with atomic_path(template) as tmp:     # an empty file: SQLite makes it a new database
        wal = Path(f"{tmp}-wal")
        try:
            with temporary_settings({PREFECT_SERVER_DATABASE_CONNECTION_URL: _SQLITE + tmp}), \
                    temporary_database_interface():
                asyncio.run(migrate())
            if wal.exists() and wal.stat().st_size:
                raise OSError(f"{tmp}: its write-ahead log was not checkpointed")
        finally:
            wal.unlink(missing_ok=True)
            Path(f"{tmp}-shm").unlink(missing_ok=True)
