#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, from Debian's slurm-wlm and munge, run as
# root with everything (config, state, logs, PID files, the munge socket and key) under one
# folder; stop it with deploy/slurm/stop.sh and the same folder.
#
#   deploy/slurm/start.sh [DIR]        # DIR defaults to /tmp/swathflow-slurm
#   export SLURM_CONF=DIR/slurm.conf   # printed on the last line; sbatch/squeue/scancel need it
#
# Ports: SLURMCTLD_PORT (default 16817) and SLURMD_PORT (default 16818), not SLURM's
# defaults. The node and controller addresses are 127.0.0.1; note that SLURM has no
# listen-address setting, so the two daemons accept connections on those ports on every
# interface (firewall them on a shared host). Munge listens on a Unix socket in DIR only.
set -euo pipefail

DIR=$(realpath -m "${1:-/tmp/swathflow-slurm}")
CTLD_PORT=${SLURMCTLD_PORT:-16817}
SLURMD_PORT=${SLURMD_PORT:-16818}
WAIT=${SLURM_START_TIMEOUT:-60}

if [ -s "$DIR/slurmctld.pid" ] && kill -0 "$(cat "$DIR/slurmctld.pid")" 2>/dev/null; then
    echo "deploy/slurm/start.sh: a cluster is already running from $DIR (stop it with deploy/slurm/stop.sh $DIR)" >&2
    exit 1
fi

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    echo "installing slurm-wlm and munge (Debian packages) ..." >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq slurm-wlm munge >/dev/null
fi

mkdir -p "$DIR"/{state,spool,munge,log}
# munge: its own key, socket, PID and log in DIR/munge, run as root like the SLURM
# daemons (--force: the socket is reachable by root only, which is all this cluster needs)
chmod 700 "$DIR/munge"
if [ ! -s "$DIR/munge/munge.key" ]; then
    dd if=/dev/urandom of="$DIR/munge/munge.key" bs=1024 count=1 status=none
fi
chmod 400 "$DIR/munge/munge.key"
SOCK="$DIR/munge/munge.socket"
munged --socket="$SOCK" --key-file="$DIR/munge/munge.key" \
    --pid-file="$DIR/munge/munged.pid" --log-file="$DIR/munge/munged.log" \
    --seed-file="$DIR/munge/munged.seed" --force

NODE=$(hostname -s)
# the CPUs slurmd itself detects and registers (`slurmd -C`): not `nproc`, which honours
# OMP_NUM_THREADS / OMP_THREAD_LIMIT and the CPU affinity of whoever runs this script (with
# OMP_NUM_THREADS=1 exported the node had 1 CPU and a second 1-CPU job stayed PENDING)
CPUS=$(slurmd -C 2>/dev/null | sed -n 's/.* CPUs=\([0-9]\+\).*/\1/p' | head -n 1 || true)
CPUS=${CPUS:-$(env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc --all)}
FREE_MB=$(awk '/MemAvailable/ {print int($2/1024)}' /proc/meminfo)
MEM_MB=$(( FREE_MB * 3 / 4 ))
cat > "$DIR/slurm.conf" <<EOF
# written by deploy/slurm/start.sh
ClusterName=swathflow
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
AuthType=auth/munge
AuthInfo=socket=$SOCK
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobCompType=jobcomp/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
KillWait=5
MinJobAge=30
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=swathflow Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF="$DIR/slurm.conf"

slurmctld -f "$SLURM_CONF" -i
slurmd -f "$SLURM_CONF" -N "$NODE"

# ready when the node is idle in the partition
deadline=$(( $(date +%s) + WAIT ))
until sinfo -h -N -o '%t' 2>/dev/null | grep -qx 'idle'; do
    if [ "$(date +%s)" -gt "$deadline" ]; then
        echo "deploy/slurm/start.sh: the node did not become idle within $WAIT s; logs in $DIR/log" >&2
        sinfo -N >&2 || true
        exit 1
    fi
    sleep 0.5
done
echo "SLURM is up: munged $(cat "$DIR/munge/munged.pid"), slurmctld $(cat "$DIR/slurmctld.pid"), slurmd $(cat "$DIR/slurmd.pid")" >&2
echo "export SLURM_CONF=$SLURM_CONF"
