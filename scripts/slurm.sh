#!/usr/bin/env bash
# One-node Slurm "cluster" for CI and for trying `silvr reconstruct --scheduler slurm` on one machine
# (Debian bookworm / Ubuntu, root, works without systemd): Debian's slurmctld, slurmd and munge, started
# in the foreground and stopped by PID (recipe: ../shared/reference/slurm_single_node.md).
#   scripts/slurm.sh up | test | down
set -euo pipefail
STATE=${STATE:-${TMPDIR:-/tmp}/slurm-ci}          # pids, daemon stdout, test outputs
NODE=$(hostname -s)

up() {
  mkdir -p "$STATE"; local t0; t0=$(date +%s)
  # A Slurm that already answers (a cluster's, or an earlier `up`) is used as it is; `down` then stops
  # nothing it did not start.
  if command -v sinfo >/dev/null && timeout 5 sinfo -h >/dev/null 2>&1; then
    : >"$STATE/pids"; echo "slurm already answering: using it"; sinfo; return 0
  fi
  if ! command -v slurmctld >/dev/null; then
    apt-get update -qq
    # policy-rc.d / no init => postinst does not start anything; munge.key is generated
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      slurmctld slurmd slurm-client munge >"$STATE/apt.log"
  fi
  local t1 CPUS MEM; t1=$(date +%s); CPUS=$(nproc)
  MEM=$(awk '/MemTotal/{print int($2/1024*0.95)}' /proc/meminfo)  # MiB, 5% headroom

  [ -s /etc/munge/munge.key ] || dd if=/dev/urandom of=/etc/munge/munge.key bs=1k count=1 status=none
  chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key
  install -d -o munge -g munge -m 0755 /run/munge          # /run is empty on a fresh boot
  install -d -o munge -g munge -m 0700 /var/log/munge /var/lib/munge
  : >"$STATE/pids"
  if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then   # systemd hosts: already running
    # setpriv execs (no fork) => $! is munged itself
    setpriv --reuid=munge --regid=munge --init-groups /usr/sbin/munged -F >"$STATE/munged.out" 2>&1 &
    echo "munged $!" >>"$STATE/pids"
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.1; done
  fi
  munge -n | unmunge >/dev/null

  install -d -o slurm -g slurm /var/lib/slurm/slurmctld /var/lib/slurm/slurmd /var/log/slurm
  cat >/etc/slurm/slurm.conf <<EOF
ClusterName=ci
SlurmctldHost=${NODE}(127.0.0.1)
AuthType=auth/munge
SlurmUser=slurm
StateSaveLocation=/var/lib/slurm/slurmctld
SlurmdSpoolDir=/var/lib/slurm/slurmd
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=/var/log/slurm/jobcomp.log
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
  # -D = foreground, backgrounded by us => $! is the daemon PID; -i = ignore missing state files
  /usr/sbin/slurmctld -D -i >"$STATE/slurmctld.out" 2>&1 & echo "slurmctld $!" >>"$STATE/pids"
  /usr/sbin/slurmd -D >"$STATE/slurmd.out" 2>&1 &           echo "slurmd $!" >>"$STATE/pids"
  local st=""
  for _ in $(seq 120); do st=$(sinfo -h -n "$NODE" -o %t 2>/dev/null || true); case $st in idle|mix|alloc) break;; esac; sleep 0.5; done
  case $st in idle|mix|alloc) ;; *) echo "node state '$st'"; tail -n 20 /var/log/slurm/*.log; return 1;; esac
  sinfo; echo "slurm up: install $((t1 - t0))s, start $(( $(date +%s) - t1 ))s"
}

down() {
  [ -f "$STATE/pids" ] || return 0
  local ids; ids=$(squeue -h -o %A 2>/dev/null || true)   # cancel every job first, else
  [ -z "$ids" ] || scancel $ids                            # slurmstepd + tasks outlive slurmd
  for _ in $(seq 30); do squeue -h 2>/dev/null | grep -q . || break; sleep 1; done
  tac "$STATE/pids" | while read -r name pid; do
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

case "${1:-}" in up) up ;; down) down ;; test) selftest ;; *) echo "usage: $0 up|test|down"; exit 2 ;; esac
