#!/usr/bin/env bash
# A real single-node Slurm cluster in a folder, for trying matflow's Slurm
# scripts and for its tests. Needs root and Debian's packages:
#
#   apt-get install slurmctld slurmd slurm-client munge
#
#   cluster/slurm/testbed.sh start DIR   # prints: export SLURM_CONF=DIR/slurm.conf
#   cluster/slurm/testbed.sh stop DIR
#
# Everything lives in DIR: its own munge key and socket, slurm.conf, state,
# spool and logs, on ports chosen free; no systemd, nothing system-wide is
# changed. proctrack/linuxproc and task/none, because cgroup plugins do not
# work in containers (jobs then "complete" without running).
set -euo pipefail

die() { echo "testbed: $*" >&2; exit 1; }
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

cmd="${1:-}"
dir="${2:-}"
[ -n "$dir" ] || die "usage: $0 start|stop DIR"

case "$cmd" in
start)
    [ "$(id -u)" = 0 ] || die "slurmd runs jobs as their users: start the testbed as root"
    for b in munged slurmctld slurmd sbatch squeue scontrol; do
        command -v "$b" >/dev/null || [ -x "/usr/sbin/$b" ] ||
            die "$b not found: apt-get install slurmctld slurmd slurm-client munge"
    done
    mkdir -p "$dir"
    dir="$(cd "$dir" && pwd)"
    mkdir -p "$dir/munge" "$dir/state" "$dir/spool" "$dir/log"
    # munge: its own key and socket, run as the munge user.
    head -c 1024 /dev/urandom > "$dir/munge/munge.key"
    chown -R munge:munge "$dir/munge"
    chmod 700 "$dir/munge"
    chmod 600 "$dir/munge/munge.key"
    runuser -u munge -- /usr/sbin/munged --force \
        --socket="$dir/munge/munge.socket" --key-file="$dir/munge/munge.key" \
        --pid-file="$dir/munge/munged.pid" --log-file="$dir/munge/munged.log" \
        --seed-file="$dir/munge/munged.seed"
    cpus="$(nproc)"
    mem="$(awk '/MemTotal/ {print int($2/1024/2)}' /proc/meminfo)"
    cat > "$dir/slurm.conf" <<CONF
ClusterName=matflow-testbed
SlurmctldHost=localhost
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$dir/munge/munge.socket
CredType=cred/munge
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/log/slurmctld.log
SlurmdLogFile=$dir/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerParameters=batch_sched_delay=0,sched_min_interval=0
ReturnToService=2
MinJobAge=3600
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
    export SLURM_CONF="$dir/slurm.conf"
    /usr/sbin/slurmctld -f "$SLURM_CONF"
    /usr/sbin/slurmd -f "$SLURM_CONF" -N localhost
    # Ready when the node takes jobs.
    for _ in $(seq 1 300); do
        state="$(sinfo -h -N -o '%T' 2>/dev/null | head -1 || true)"
        case "$state" in idle|mixed|allocated) echo "export SLURM_CONF=$SLURM_CONF"; exit 0 ;; esac
        sleep 0.1
    done
    die "the node did not come up (state '${state:-none}'); see $dir/log"
    ;;
stop)
    for f in "$dir/slurmd.pid" "$dir/slurmctld.pid" "$dir/munge/munged.pid"; do
        [ -f "$f" ] && kill "$(cat "$f")" 2>/dev/null || true
    done
    ;;
*)
    die "usage: $0 start|stop DIR"
    ;;
esac
