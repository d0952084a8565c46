#!/usr/bin/env bash
# Stop what deploy/prefect/start.sh started from DIR, by the PIDs in its PID files: the
# worker (with its process group, so flow runs it started go too), then the server.
#
#   deploy/prefect/stop.sh [DIR]       # DIR defaults to /tmp/swathflow-prefect
set -uo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-prefect}")
WAIT=${PREFECT_STOP_TIMEOUT:-30}

live_in_group() {  # members of process group $1 that are not zombies
    ps -eo pgid=,stat= | awk -v g="$1" '$1 == g && $2 !~ /^Z/' | grep -q .
}

stop_group() {  # stop_group PIDFILE: INT (Prefect's clean shutdown), then TERM the group
    local file=$1 pid sig
    [ -s "$file" ] || return 0
    pid=$(cat "$file")
    for sig in INT TERM; do
        live_in_group "$pid" || break
        kill -"$sig" -- "-$pid" 2>/dev/null
        for _ in $(seq $(( WAIT * 5 ))); do
            live_in_group "$pid" || break
            sleep 0.1
        done
    done
    if live_in_group "$pid"; then
        echo "deploy/prefect/stop.sh: $(basename "$file" .pid) ($pid) did not stop in $WAIT s: killing it" >&2
        kill -KILL -- "-$pid" 2>/dev/null
    fi
    rm -f "$file"
}

stop_group "$DIR/worker.pid"
stop_group "$DIR/server.pid"
echo "Prefect in $DIR stopped" >&2
