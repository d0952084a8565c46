#!/usr/bin/env bash
# A Prefect server and a process worker for swathflow's inbox deployment, both on loopback,
# logs and PID files under DIR. Stop them with deploy/prefect/stop.sh DIR.
#
#   eval "$(deploy/postgres/start.sh)"     # the database (PREFECT_API_DATABASE_CONNECTION_URL)
#   deploy/prefect/start.sh [DIR]          # DIR defaults to /tmp/swathflow-prefect
#   export PREFECT_API_URL=http://127.0.0.1:14200/api    # printed on the last line
#
# PREFECT_PORT sets the server's port (default 14200, not Prefect's 4200); PREFECT_BIN the
# `prefect` executable (default: the one on PATH). Without PREFECT_API_DATABASE_CONNECTION_URL
# the server falls back to SQLite, which logs "database is locked" under a scheduled
# workload: use PostgreSQL for anything beyond a trial. The worker runs flow runs of the
# work pool swathflow-process (created here if missing) from SWATHFLOW_HOME (the repository).
set -euo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-prefect}")
PORT=${PREFECT_PORT:-14200}
PREFECT=${PREFECT_BIN:-prefect}
WAIT=${PREFECT_START_TIMEOUT:-180}
POOL=${SWATHFLOW_POOL:-swathflow-process}
HERE=$(cd "$(dirname "$0")" && pwd)
export SWATHFLOW_HOME=${SWATHFLOW_HOME:-$(dirname "$(dirname "$HERE")")}
export PREFECT_HOME=${PREFECT_HOME:-$DIR/home}
export PREFECT_API_URL="http://127.0.0.1:$PORT/api"
export PREFECT_SERVER_ANALYTICS_ENABLED=false PREFECT_SERVER_UI_ENABLED=false
export PREFECT_LOGGING_LEVEL=${PREFECT_LOGGING_LEVEL:-INFO}

if [ -s "$DIR/server.pid" ] && kill -0 "$(cat "$DIR/server.pid")" 2>/dev/null; then
    echo "deploy/prefect/start.sh: a server is already running from $DIR (stop it with deploy/prefect/stop.sh $DIR)" >&2
    exit 1
fi
if [ -z "${PREFECT_API_DATABASE_CONNECTION_URL:-}" ]; then
    echo "deploy/prefect/start.sh: warning: PREFECT_API_DATABASE_CONNECTION_URL is not set: SQLite (see deploy/README.md)" >&2
fi
mkdir -p "$DIR" "$PREFECT_HOME"

# each process leads its own process group (setsid): stop.sh ends it with its children
setsid "$PREFECT" server start --host 127.0.0.1 --port "$PORT" --no-ui --analytics-off \
    >"$DIR/server.log" 2>&1 < /dev/null &
echo $! > "$DIR/server.pid"
deadline=$(( $(date +%s) + WAIT ))
until curl -sf "http://127.0.0.1:$PORT/api/health" >/dev/null 2>&1; do
    if ! kill -0 "$(cat "$DIR/server.pid")" 2>/dev/null || [ "$(date +%s)" -gt "$deadline" ]; then
        echo "deploy/prefect/start.sh: the server did not answer within $WAIT s; see $DIR/server.log" >&2
        tail -5 "$DIR/server.log" >&2
        exit 1
    fi
    sleep 0.5
done

"$PREFECT" work-pool inspect "$POOL" >/dev/null 2>&1 \
    || "$PREFECT" work-pool create "$POOL" --type process >/dev/null
setsid "$PREFECT" worker start --pool "$POOL" --name "$POOL-worker" \
    >"$DIR/worker.log" 2>&1 < /dev/null &
echo $! > "$DIR/worker.pid"
deadline=$(( $(date +%s) + WAIT ))
until grep -q "started" "$DIR/worker.log" 2>/dev/null; do
    if ! kill -0 "$(cat "$DIR/worker.pid")" 2>/dev/null || [ "$(date +%s)" -gt "$deadline" ]; then
        echo "deploy/prefect/start.sh: the worker did not start within $WAIT s; see $DIR/worker.log" >&2
        tail -5 "$DIR/worker.log" >&2
        exit 1
    fi
    sleep 0.5
done
echo "Prefect is up on 127.0.0.1:$PORT: server $(cat "$DIR/server.pid"), worker $(cat "$DIR/worker.pid") (pool $POOL)" >&2
echo "export PREFECT_API_URL=$PREFECT_API_URL"
