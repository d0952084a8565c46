#!/usr/bin/env bash
# A PostgreSQL server for Prefect's database, from Debian's postgresql package, with its
# data, socket, log and PID under DIR, listening on 127.0.0.1 only. Stop it with
# deploy/postgres/stop.sh DIR.
#
#   deploy/postgres/start.sh [DIR]     # DIR defaults to /tmp/swathflow-postgres
#   export PREFECT_API_DATABASE_CONNECTION_URL=postgresql+asyncpg://prefect:...@127.0.0.1:15432/prefect
#                                      # printed on the last line (the password is in DIR/password)
#
# POSTGRES_PORT sets the port (default 15432, not PostgreSQL's 5432). The server runs as the
# `postgres` user, so DIR and its parents must be reachable by that user (e.g. under /tmp
# or /srv, not under a folder only root may enter).
set -euo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-postgres}")
PORT=${POSTGRES_PORT:-15432}
WAIT=${POSTGRES_START_TIMEOUT:-60}

if ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
    echo "installing postgresql (Debian package) ..." >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq postgresql >/dev/null
fi
BIN=$(dirname "$(ls -d /usr/lib/postgresql/*/bin/initdb | sort -V | tail -1)")
as_pg() { runuser -u postgres -- "$@"; }

if [ -s "$DIR/postgres.pid" ] && kill -0 "$(cat "$DIR/postgres.pid")" 2>/dev/null; then
    echo "deploy/postgres/start.sh: a server is already running from $DIR (stop it with deploy/postgres/stop.sh $DIR)" >&2
    exit 1
fi
mkdir -p "$DIR"
chown postgres: "$DIR" && chmod 700 "$DIR"
if ! as_pg test -w "$DIR"; then
    echo "deploy/postgres/start.sh: the postgres user cannot reach $DIR: choose a folder whose parents it may enter" >&2
    exit 1
fi
if [ ! -s "$DIR/password" ]; then
    umask 077
    head -c 18 /dev/urandom | base64 | tr '+/' '-_' > "$DIR/password"
    chown postgres: "$DIR/password"
fi
PASSWORD=$(cat "$DIR/password")
if [ ! -s "$DIR/data/PG_VERSION" ]; then
    as_pg "$BIN/initdb" -D "$DIR/data" -U postgres --auth-local=peer --auth-host=scram-sha-256 \
        -E UTF8 --locale=C.UTF-8 >"$DIR/initdb.log" 2>&1 \
        || { echo "deploy/postgres/start.sh: initdb failed; see $DIR/initdb.log" >&2; exit 1; }
fi
mkdir -p "$DIR/socket" && chown postgres: "$DIR/socket"
as_pg "$BIN/pg_ctl" -D "$DIR/data" -l "$DIR/postgres.log" -w -t "$WAIT" \
    -o "-c listen_addresses=127.0.0.1 -p $PORT -k $DIR/socket -c max_connections=200" start >/dev/null \
    || { echo "deploy/postgres/start.sh: the server did not start within $WAIT s; see $DIR/postgres.log" >&2; exit 1; }
head -1 "$DIR/data/postmaster.pid" > "$DIR/postgres.pid"

psql_pg() { as_pg psql -h "$DIR/socket" -p "$PORT" -U postgres -d postgres -v ON_ERROR_STOP=1 -qAt "$@"; }
deadline=$(( $(date +%s) + WAIT ))
until psql_pg -c 'select 1' >/dev/null 2>&1; do
    [ "$(date +%s)" -gt "$deadline" ] && { echo "deploy/postgres/start.sh: no answer within $WAIT s" >&2; exit 1; }
    sleep 0.2
done
if [ "$(psql_pg -c "select 1 from pg_roles where rolname='prefect'")" != 1 ]; then
    psql_pg -c "create role prefect login password '$PASSWORD'"
fi
if [ "$(psql_pg -c "select 1 from pg_database where datname='prefect'")" != 1 ]; then
    psql_pg -c "create database prefect owner prefect"
fi
echo "PostgreSQL is up on 127.0.0.1:$PORT: postgres $(cat "$DIR/postgres.pid")" >&2
echo "export PREFECT_API_DATABASE_CONNECTION_URL=postgresql+asyncpg://prefect:$PASSWORD@127.0.0.1:$PORT/prefect"
