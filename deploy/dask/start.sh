#!/usr/bin/env bash
# A standalone Dask cluster from Dask's own command lines: one `dask scheduler` and N
# `dask worker` processes (one single-threaded worker each, with its nanny), all on
# loopback, logs and PID files under DIR. Stop it with deploy/dask/stop.sh DIR.
#
#   deploy/dask/start.sh [DIR] [N]     # DIR defaults to /tmp/swathflow-dask-cluster, N to 2
#   swathflow run MISSION --out OUT --dask-address tcp://127.0.0.1:18786   (printed last)
#
# DASK_SCHEDULER_PORT (default 18786) sets the scheduler's port; DASK_BIN the `dask`
# executable (default: the one on PATH, which must import swathflow). Workers read the Dask
# configuration in this folder (local.yaml: memory limits, retries) unless DASK_CONFIG is set.
set -euo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-dask-cluster}")
N=${2:-2}
PORT=${DASK_SCHEDULER_PORT:-18786}
DASK=${DASK_BIN:-dask}
WAIT=${DASK_START_TIMEOUT:-60}
HERE=$(cd "$(dirname "$0")" && pwd)
export DASK_CONFIG=${DASK_CONFIG:-$HERE}
export DASK_LOGGING__DISTRIBUTED=info   # readiness is read from the startup lines of the logs

if [ -s "$DIR/scheduler.pid" ] && kill -0 "$(cat "$DIR/scheduler.pid")" 2>/dev/null; then
    echo "deploy/dask/start.sh: a cluster is already running from $DIR (stop it with deploy/dask/stop.sh $DIR)" >&2
    exit 1
fi
mkdir -p "$DIR"
ADDR="tcp://127.0.0.1:$PORT"

wait_for() {  # wait_for WHAT LOGFILE PATTERN PID
    local deadline=$(( $(date +%s) + WAIT ))
    until grep -q "$3" "$2" 2>/dev/null; do
        if ! kill -0 "$4" 2>/dev/null || [ "$(date +%s)" -gt "$deadline" ]; then
            echo "deploy/dask/start.sh: $1 did not start within $WAIT s; see $2" >&2
            tail -5 "$2" >&2 || true
            exit 1
        fi
        sleep 0.2
    done
}

# each process leads its own process group (setsid): stop.sh ends a worker with its nanny's child
setsid "$DASK" scheduler --host 127.0.0.1 --port "$PORT" --no-dashboard --dashboard-address 127.0.0.1:0 \
    >"$DIR/scheduler.log" 2>&1 < /dev/null &
echo $! > "$DIR/scheduler.pid"
wait_for scheduler "$DIR/scheduler.log" "Scheduler at:" "$!"

for i in $(seq 1 "$N"); do
    setsid "$DASK" worker "$ADDR" --host 127.0.0.1 --nthreads 1 --nworkers 1 --nanny \
        --no-dashboard --dashboard-address 127.0.0.1:0 --name "worker-$i" --local-directory "$DIR/worker-$i" \
        >"$DIR/worker-$i.log" 2>&1 < /dev/null &
    echo $! > "$DIR/worker-$i.pid"
done
for i in $(seq 1 "$N"); do
    wait_for "worker $i" "$DIR/worker-$i.log" "Registered to:" "$(cat "$DIR/worker-$i.pid")"
done
echo "Dask is up: scheduler $(cat "$DIR/scheduler.pid"), $N workers ($(cat "$DIR"/worker-*.pid | tr '\n' ' '))" >&2
echo "$ADDR"
