#!/usr/bin/env bash
# Stop the cluster deploy/slurm/start.sh started from DIR: cancel its jobs, then stop
# slurmd, slurmctld and munged by the PIDs in their PID files (nothing else is touched).
#
#   deploy/slurm/stop.sh [DIR]         # DIR defaults to /tmp/swathflow-slurm
set -uo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-slurm}")
WAIT=${SLURM_STOP_TIMEOUT:-30}
export SLURM_CONF="$DIR/slurm.conf"

running() { local s; s=$(ps -o stat= -p "$1" 2>/dev/null) && [ "${s:0:1}" != Z ]; }  # zombies are not

stop_pid() {  # stop_pid NAME PIDFILE: TERM, wait up to WAIT s, then KILL
    local name=$1 file=$2 pid
    [ -s "$file" ] || return 0
    pid=$(cat "$file")
    if running "$pid"; then
        kill -TERM "$pid"
        for _ in $(seq $(( WAIT * 10 ))); do
            running "$pid" || break
            sleep 0.1
        done
        if running "$pid"; then
            echo "deploy/slurm/stop.sh: $name ($pid) did not stop in $WAIT s: killing it" >&2
            kill -KILL "$pid"
        fi
    fi
    rm -f "$file"
}

if [ -s "$DIR/slurmctld.pid" ] && kill -0 "$(cat "$DIR/slurmctld.pid")" 2>/dev/null; then
    # jobs first, so slurmd reaps their processes (job steps are its children)
    scancel --partition swathflow 2>/dev/null || true
    for _ in $(seq $(( WAIT * 2 ))); do
        [ -z "$(squeue -h -o %i 2>/dev/null)" ] && break
        sleep 0.5
    done
fi
stop_pid slurmd "$DIR/slurmd.pid"
stop_pid slurmctld "$DIR/slurmctld.pid"
stop_pid munged "$DIR/munge/munged.pid"
echo "SLURM in $DIR stopped" >&2
