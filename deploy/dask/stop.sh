#!/usr/bin/env bash
# Stop the cluster deploy/dask/start.sh started from DIR, by the PIDs in its PID files:
# the workers (each with its process group: nanny and worker process), then the scheduler.
#
#   deploy/dask/stop.sh [DIR]          # DIR defaults to /tmp/swathflow-dask-cluster
set -uo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-dask-cluster}")
WAIT=${DASK_STOP_TIMEOUT:-30}

live_in_group() {  # members of process group $1 that are not zombies
    ps -eo pgid=,stat= | awk -v g="$1" '$1 == g && $2 !~ /^Z/' | grep -q .
}

stop_group() {  # stop_group PIDFILE: TERM the group the PID leads, wait, then KILL it
    local file=$1 pid
    [ -s "$file" ] || return 0
    pid=$(cat "$file")
    if live_in_group "$pid"; then
        kill -TERM -- "-$pid" 2>/dev/null
        for _ in $(seq $(( WAIT * 10 ))); do
            live_in_group "$pid" || break
            sleep 0.1
        done
        if live_in_group "$pid"; then
            echo "deploy/dask/stop.sh: $(basename "$file" .pid) ($pid) did not stop in $WAIT s: killing it" >&2
            kill -KILL -- "-$pid" 2>/dev/null
        fi
    fi
    rm -f "$file"
}

for f in "$DIR"/worker-*.pid; do
    [ -e "$f" ] && stop_group "$f"
done
stop_group "$DIR/scheduler.pid"
echo "Dask in $DIR stopped" >&2
