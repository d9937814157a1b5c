#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, from Debian's packages (slurm-wlm, munge):
# munged, slurmctld (the controller) and slurmd (one compute node with the machine's
# cores and memory, as `slurmd -C` reports them), partition "main" (the one
# workflow/profiles/slurm submits to). No accounting database: job status comes from
# squeue, so completed jobs are kept in the controller for MinJobAge (10 min).
#
#   scripts/slurm-local.sh start     # write /etc/slurm/slurm.conf, start the daemons, wait for the node
#   scripts/slurm-local.sh status    # sinfo, or exit 1 when the controller does not answer
#   scripts/slurm-local.sh stop      # stop the daemons this script started
#
# Runs as root (or with sudo). The configuration lives in /etc/slurm, where srun and job
# steps look for it; state, logs and pid files under /var/lib/chisel-slurm.
set -euo pipefail

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
STATE=/var/lib/chisel-slurm
CONF=/etc/slurm/slurm.conf
PARTITION=${SLURM_LOCAL_PARTITION:-main}

need() {
  for bin in munged slurmctld slurmd sinfo scontrol; do
    command -v "$bin" >/dev/null 2>&1 || PATH="$PATH:/usr/sbin"
    command -v "$bin" >/dev/null 2>&1 || {
      echo "slurm-local: $bin not found; install Debian's slurm-wlm and munge (scripts/setup.sh)" >&2
      exit 2
    }
  done
}

pid_alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

write_conf() {
  local host node mem
  host=$(hostname -s)
  # "NodeName=vm CPUs=2 Boards=1 SocketsPerBoard=1 CoresPerSocket=2 ThreadsPerCore=1 RealMemory=24105"
  node=$(slurmd -C | head -n1)
  mem=$(sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' <<<"$node")
  mem=$((mem * 95 / 100))  # leave the OS its share
  node=$(sed "s/RealMemory=[0-9]*/RealMemory=$mem/" <<<"$node")
  $SUDO mkdir -p /etc/slurm "$STATE"/{ctld,slurmd,log}
  $SUDO tee "$CONF" >/dev/null <<CONFEOF
# Written by scripts/slurm-local.sh: a single-node cluster for Endoscopic Chisel.
ClusterName=chisel
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/slurmd
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
ReturnToService=2
MinJobAge=600
SlurmdTimeout=120
InactiveLimit=0
KillWait=10
$node State=UNKNOWN
PartitionName=$PARTITION Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONFEOF
  # srun/sbatch look for cgroup.conf only with cgroup plugins; none here.
}

start() {
  need
  if pid_alive "$STATE/slurmctld.pid" && scontrol ping >/dev/null 2>&1; then
    echo "slurm-local: already running"; sinfo; return 0
  fi
  write_conf
  if ! pgrep -x munged >/dev/null 2>&1; then
    [ -f /etc/munge/munge.key ] || $SUDO mungekey --create 2>/dev/null || $SUDO /usr/sbin/create-munge-key -f
    $SUDO mkdir -p /run/munge /var/log/munge /var/lib/munge
    $SUDO chown munge:munge /run/munge /var/log/munge /var/lib/munge /etc/munge /etc/munge/munge.key 2>/dev/null || true
    $SUDO chmod 0400 /etc/munge/munge.key
    $SUDO -u munge /usr/sbin/munged 2>/dev/null || $SUDO runuser -u munge -- /usr/sbin/munged
    touch "$STATE/started-munged"
  fi
  # -c: start clean (no jobs, nodes or reservations from an earlier cluster's saved state)
  $SUDO /usr/sbin/slurmctld -c
  $SUDO /usr/sbin/slurmd
  for _ in $(seq 1 60); do
    if sinfo -h -o "%t" 2>/dev/null | grep -qE "^(idle|mix|alloc)"; then
      echo "slurm-local: cluster up"; sinfo; return 0
    fi
    sleep 1
  done
  echo "slurm-local: the node did not come up; logs in $STATE/log" >&2
  sinfo >&2 || true
  tail -n 20 "$STATE/log/slurmctld.log" "$STATE/log/slurmd.log" >&2 || true
  exit 1
}

# Stop one daemon by the pid in its pid file: SIGTERM, wait for the *process* (slurmd
# removes its pid file at the start of a shutdown that can hang), SIGKILL after 20 s.
stop_daemon() {
  local pidfile=$1 pid
  [ -f "$pidfile" ] || return 0
  pid=$(cat "$pidfile")
  kill -0 "$pid" 2>/dev/null || { $SUDO rm -f "$pidfile"; return 0; }
  $SUDO kill "$pid" 2>/dev/null || true
  for _ in $(seq 1 40); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.5; done
  echo "slurm-local: pid $pid ($pidfile) did not stop on SIGTERM; SIGKILL" >&2
  $SUDO kill -9 "$pid" 2>/dev/null || true
  $SUDO rm -f "$pidfile"
}

stop() {
  # Jobs first, while the controller answers: a job step left running when the daemons go
  # retries its completion message for ever and keeps slurmd from shutting down.
  if scontrol ping >/dev/null 2>&1; then
    scancel --partition="$PARTITION" 2>/dev/null || true
    for _ in $(seq 1 30); do
      [ -z "$(squeue -h -p "$PARTITION" -t RUNNING,COMPLETING,PENDING -o %i 2>/dev/null)" ] && break
      sleep 1
    done
  fi
  stop_daemon "$STATE/slurmd.pid"
  stop_daemon "$STATE/slurmctld.pid"
  if [ -f "$STATE/started-munged" ]; then
    stop_daemon /run/munge/munged.pid
    rm -f "$STATE/started-munged"
  fi
  echo "slurm-local: stopped"
}

status() {
  need
  if scontrol ping >/dev/null 2>&1 && sinfo >/dev/null 2>&1; then sinfo; else
    echo "slurm-local: not running"; exit 1
  fi
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) status ;;
  *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
