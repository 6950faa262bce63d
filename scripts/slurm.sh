#!/usr/bin/env bash
# A private one-node Slurm "cluster" for CI and for trying `silvr reconstruct --scheduler slurm` on one machine
# (Debian bookworm / Ubuntu, root, works without systemd): Debian's slurmctld, slurmd and munged, started in
# the foreground and stopped by PID (recipe: ../shared/reference/slurm_single_node.md).
#   STATE=DIR scripts/slurm.sh up | conf | test | down
#
# Private means it never touches a Slurm it did not start: everything it writes is under $STATE — its own
# slurm.conf (first line: the marker below), munge key and socket, state, spool, logs, pids — and its daemons
# listen on their own ports (SILVR_SLURM_PORT, default 6917, and the next one for slurmd), so a cluster's
# /etc/slurm, /etc/munge, daemons and jobs are left alone. Commands reach it through SLURM_CONF:
#   export SLURM_CONF=$(STATE=DIR scripts/slurm.sh conf)
set -euo pipefail
STATE=${STATE:-${TMPDIR:-/tmp}/slurm-ci}           # everything of this Slurm lives here
STATE=$(realpath -m "$STATE")                       # absolute: it is written into slurm.conf
CONF=$STATE/etc/slurm.conf
MARK="# SiLVR Studio scripts/slurm.sh: a private one-node Slurm; every file it uses is under this folder."
PORT=${SILVR_SLURM_PORT:-6917}
NODE=$(hostname -s)
# Every client command below (sinfo, squeue, scancel, sbatch) talks to this Slurm only.
export SLURM_CONF=$CONF

ours() { [ -f "$CONF" ] && [ "$(head -n 1 "$CONF")" = "$MARK" ]; }

# Whether PID is a daemon this script started on $STATE (its command line names $STATE): a stale pids
# file's numbers may belong to other processes by now.
mine() { tr '\0' ' ' <"/proc/$1/cmdline" 2>/dev/null | grep -qF -- "$STATE/"; }

# PIDs from $STATE/pids that are still ours and alive
alive() { [ -f "$STATE/pids" ] && awk '{print $2}' "$STATE/pids" | while read -r pid; do mine "$pid" && echo "$pid"; done; }

up() {
  if [ -e "$CONF" ] && ! ours; then
    echo "refusing: $CONF exists and scripts/slurm.sh did not write it (no '$MARK' first line); choose another STATE" >&2
    return 1
  fi
  if [ -n "$(alive || true)" ]; then
    echo "already up (STATE=$STATE): SLURM_CONF=$CONF"; sinfo; return 0
  fi
  [ "$(id -u)" = 0 ] || { echo "scripts/slurm.sh up needs root (slurmd starts jobs as their users)" >&2; return 1; }
  mkdir -p "$STATE"; local t0; t0=$(date +%s)
  if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null \
     || ! command -v sbatch >/dev/null; then
    command -v apt-get >/dev/null || { echo "install slurmctld, slurmd, slurm-client and munge (no apt-get here)" >&2; return 1; }
    apt-get update -qq
    # policy-rc.d / no init => postinst does not start anything; with systemd the packages' own units may
    # start (with the packages' config), which this script neither uses nor stops.
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      slurmctld slurmd slurm-client munge >"$STATE/apt.log"
  fi
  local t1 CPUS MEM; t1=$(date +%s); CPUS=$(nproc)
  MEM=$(awk '/MemTotal/{print int($2/1024*0.95)}' /proc/meminfo)  # MiB, 5% headroom

  # A munged of our own (its key, socket, pid, log and seed under $STATE/munge), run as root: the
  # system's munge (its key, /run/munge) is not used. munged wants its folder closed to others.
  install -d -m 0700 "$STATE/munge" "$STATE/ctld" "$STATE/spool" "$STATE/log" "$STATE/etc"
  [ -s "$STATE/munge/munge.key" ] || dd if=/dev/urandom of="$STATE/munge/munge.key" bs=1k count=1 status=none
  chmod 400 "$STATE/munge/munge.key"
  local sock=$STATE/munge/munge.socket
  : >"$STATE/pids"
  # --force: munged otherwise refuses to run as root.
  /usr/sbin/munged -F --force --socket="$sock" --key-file="$STATE/munge/munge.key" \
    --pid-file="$STATE/munge/munged.pid" --log-file="$STATE/munge/munged.log" \
    --seed-file="$STATE/munge/munged.seed" >"$STATE/munged.out" 2>&1 &
  echo "munged $!" >>"$STATE/pids"
  for _ in $(seq 50); do munge -S "$sock" -n 2>/dev/null | unmunge -S "$sock" >/dev/null 2>&1 && break; sleep 0.1; done
  munge -S "$sock" -n | unmunge -S "$sock" >/dev/null || { cat "$STATE/munged.out"; return 1; }

  {
    echo "$MARK"
    cat <<EOF
ClusterName=silvr-ci
SlurmctldHost=${NODE}(127.0.0.1)
SlurmctldPort=${PORT}
SlurmdPort=$((PORT + 1))
AuthType=auth/munge
AuthInfo=socket=${sock}
CredType=cred/munge
SlurmUser=root
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/log/jobcomp.log
MpiDefault=none
MailProg=/bin/true
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU=$((MEM / CPUS))
ReturnToService=2
MinJobAge=3600
NodeName=${NODE} NodeAddr=127.0.0.1 CPUs=${CPUS} RealMemory=${MEM} State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
  } >"$CONF.tmp"
  mv "$CONF.tmp" "$CONF"
  # -D = foreground, backgrounded by us => $! is the daemon PID; -i = ignore missing state files
  /usr/sbin/slurmctld -D -i -f "$CONF" >"$STATE/slurmctld.out" 2>&1 & echo "slurmctld $!" >>"$STATE/pids"
  /usr/sbin/slurmd -D -f "$CONF" >"$STATE/slurmd.out" 2>&1 &           echo "slurmd $!" >>"$STATE/pids"
  local st=""
  for _ in $(seq 120); do st=$(sinfo -h -n "$NODE" -o %t 2>/dev/null || true); case $st in idle|mix|alloc) break;; esac; sleep 0.5; done
  case $st in idle|mix|alloc) ;; *) echo "node state '$st'"; tail -n 20 "$STATE"/log/*.log "$STATE"/*.out; return 1;; esac
  sinfo; echo "slurm up: install $((t1 - t0))s, start $(( $(date +%s) - t1 ))s; SLURM_CONF=$CONF"
}

down() {
  [ -f "$STATE/pids" ] || return 0
  # Only our own cluster's jobs (SLURM_CONF is ours), and only when the config is the one `up` wrote.
  if ours; then
    local ids; ids=$(squeue -h -o %A 2>/dev/null || true)   # cancel every job first, else
    [ -z "$ids" ] || scancel $ids                            # slurmstepd + tasks outlive slurmd
    for _ in $(seq 30); do squeue -h 2>/dev/null | grep -q . || break; sleep 1; done
  fi
  tac "$STATE/pids" | while read -r name pid; do
    mine "$pid" || continue
    kill -TERM "$pid" 2>/dev/null || continue
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    if kill -0 "$pid" 2>/dev/null; then kill -KILL "$pid"; fi
    echo "stopped $name ($pid)"
  done
  rm -f "$STATE/pids"
}

# wait for a (array) job to leave the queue, then fail if any task is not COMPLETED
wait_job() {
  local jid=$1 s
  while squeue -h -j "$jid" 2>/dev/null | grep -q .; do sleep 1; done
  s=$(scontrol -o show job "$jid" | awk '{l=""; for (i = 1; i <= NF; i++)
        if ($i ~ /^(JobId|ArrayTaskId|JobState|ExitCode)=/) l = l " " $i; print l}')
  echo "$s" | tee "$STATE/job_$jid.states"
  [ -n "$s" ] && ! grep -v 'JobState=COMPLETED ' <<<"$s" >/dev/null
}

selftest() {
  ours || { echo "no Slurm of scripts/slurm.sh at $CONF: run 'STATE=$STATE scripts/slurm.sh up' first" >&2; return 1; }
  mkdir -p "$STATE/t" && cd "$STATE/t" && rm -f ./*.out
  srun -n1 hostname
  jid=$(sbatch --parsable --array=0-3 -o 'arr_%A_%a.out' --wrap 'echo task $SLURM_ARRAY_TASK_ID; sleep 2')
  wait_job "$jid"; [ "$(cat arr_"${jid}"_*.out | wc -l)" = 4 ]; cat arr_"${jid}"_*.out
  sbatch --wait -o 'w_%j.out' --wrap 'sleep 1'                          # rc 0
  jid=$(sbatch --parsable --array=0-3 -o 'f_%A_%a.out' --wrap '[ $SLURM_ARRAY_TASK_ID = 2 ] && exit 3; true')
  if wait_job "$jid"; then echo "expected a FAILED task"; return 1; fi
  set +e; sbatch --wait --array=0-1 -o 'f2_%A_%a.out' --wrap 'exit $((SLURM_ARRAY_TASK_ID*3))'; rc=$?; set -e
  [ "$rc" = 3 ] || { echo "sbatch --wait rc=$rc, expected 3"; return 1; }   # = max task exit code
  sacct -j "$jid" 2>&1 | head -1 || true                               # no slurmdbd => disabled
  echo "selftest OK"
}

case "${1:-}" in
  up) up ;;
  conf) echo "$CONF" ;;
  down) down ;;
  test) selftest ;;
  *) echo "usage: STATE=DIR $0 up|conf|test|down"; exit 2 ;;
esac
