#!/usr/bin/env bash
# Stop the server deploy/postgres/start.sh started from DIR: pg_ctl's fast shutdown, then,
# if it is still up after the time-out, the postmaster by its recorded PID. Data is kept.
#
#   deploy/postgres/stop.sh [DIR]      # DIR defaults to /tmp/swathflow-postgres
set -uo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-postgres}")
WAIT=${POSTGRES_STOP_TIMEOUT:-60}
running() { local s; s=$(ps -o stat= -p "$1" 2>/dev/null) && [ "${s:0:1}" != Z ]; }  # zombies are not
[ -s "$DIR/postgres.pid" ] || { echo "no server recorded in $DIR" >&2; exit 0; }
PID=$(cat "$DIR/postgres.pid")
if running "$PID"; then
    BIN=$(dirname "$(ls -d /usr/lib/postgresql/*/bin/pg_ctl | sort -V | tail -1)")
    runuser -u postgres -- "$BIN/pg_ctl" -D "$DIR/data" -m fast -w -t "$WAIT" stop >/dev/null 2>&1 \
        || kill -INT "$PID" 2>/dev/null   # fast shutdown by signal when pg_ctl cannot
    for _ in $(seq $(( WAIT * 10 ))); do
        running "$PID" || break
        sleep 0.1
    done
    if running "$PID"; then
        echo "deploy/postgres/stop.sh: postgres ($PID) did not stop in $WAIT s: killing it" >&2
        kill -KILL "$PID"
    fi
fi
rm -f "$DIR/postgres.pid"
echo "PostgreSQL in $DIR stopped" >&2
