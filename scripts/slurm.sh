#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for the test suite (tests/test_slurm.py) and for trying the SLURM
# profile before a real cluster (docs/slurm.md): Debian's slurmctld, slurmd and munge, configured for localhost,
# without an accounting database. Its configuration is /etc/slurm/slurm.conf (and gres.conf), where every SLURM
# command looks (the executor plugin's job step drops $SLURM_CONF before its srun); a slurm.conf this script did not
# write is never replaced. Key, state and logs stay in /tmp/guiding-slurm. The node has two partitions, cpu (the
# default) and gpu, and two stand-in GPUs (character devices like /dev/null): enough to schedule --gpus requests,
# not to run CUDA.
#
#   scripts/slurm.sh start     install what is missing (apt-get), configure, start munged, slurmctld and slurmd
#   scripts/slurm.sh status    exit status 0 when all three run and the controller answers
#   scripts/slurm.sh stop      cancel the cluster's jobs and stop the daemons this script started
#
# Needs root (slurmd starts every job as its user). A failure is one line on stderr and exit status 2.
set -euo pipefail

DIR=/tmp/guiding-slurm
CONF=/etc/slurm/slurm.conf
MARK="# Written by scripts/slurm.sh of guiding: a single-node test cluster on localhost."
NODE=$(hostname -s)
GPUS=2
GPU_TYPE=standin
PACKAGES=(slurmctld slurmd slurm-client munge)

fail() {
  echo "slurm: error: $*" >&2
  exit 2
}

# The last error a daemon logged, for the one-line failure (slurmd's complaints that Debian's MPI plugins lack
# PMIx come with every start).
last_error() {
  grep -h -i -E "error|fatal" "$@" 2>/dev/null | grep -v -i -E "pmix|MPI:" | tail -n 1 | cut -c1-200 || true
}

# A daemon runs when its pid file names a live process of that name (not a recycled pid).
alive() {
  local name=$1 pidfile=$2 pid
  [ -s "$pidfile" ] || return 1
  pid=$(cat "$pidfile")
  [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$name" ]
}

running() {
  alive munged "$DIR/munge/munged.pid" && alive slurmctld "$DIR/slurmctld.pid" && alive slurmd "$DIR/slurmd.pid" &&
    scontrol ping >/dev/null 2>&1
}

install() {
  local missing=()
  for command in slurmctld slurmd sbatch munged; do
    command -v "$command" >/dev/null || missing+=("$command")
  done
  [ ${#missing[@]} -eq 0 ] && return
  echo "slurm: installing ${PACKAGES[*]} (missing: ${missing[*]})" >&2
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      "${PACKAGES[@]}"; } >"$DIR/apt.log" 2>&1 ||
    fail "apt-get could not install ${PACKAGES[*]}: $(tail -n 1 "$DIR/apt.log")"
  # Under systemd the packages' own services start at boot with this configuration: two controllers on one port.
  if [ -d /run/systemd/system ]; then
    systemctl disable --now munge slurmctld slurmd >/dev/null 2>&1 || true
  fi
}

configure() {
  mkdir -p "$DIR/state" "$DIR/spool"
  # munged insists on a key only it can read and on a socket folder that everyone can enter.
  mkdir -p -m 0755 "$DIR/munge"
  chmod 0755 "$DIR" "$DIR/munge"
  if [ ! -s "$DIR/munge/munge.key" ]; then
    (umask 077 && head -c 1024 /dev/urandom >"$DIR/munge/munge.key")
  fi
  for i in $(seq 0 $((GPUS - 1))); do
    # gres/gpu drops GPUs without a device file; with task/none nothing opens these.
    [ -c "$DIR/gpu$i" ] || mknod "$DIR/gpu$i" c 1 3 || fail "cannot make the stand-in GPU device $DIR/gpu$i"
  done
  local hardware
  hardware=$(slurmd -C | head -n 1) || fail "slurmd -C cannot read this machine's CPUs and memory"
  mkdir -p "$(dirname "$CONF")"
  cat >"$CONF" <<EOF
$MARK
ClusterName=guiding
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$DIR/munge/munge.socket
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
# No cgroups (containers rarely allow them) and no accounting database: sacct has nothing to report, so clients
# ask squeue, which knows a finished job for MinJobAge seconds (an hour: the tests read a whole run's jobs after it).
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MinJobAge=3600
KillWait=5
ReturnToService=2
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
GresTypes=gpu
$hardware NodeAddr=127.0.0.1 Gres=gpu:$GPU_TYPE:$GPUS State=UNKNOWN
PartitionName=cpu Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$NODE MaxTime=INFINITE State=UP
EOF
  echo "NodeName=$NODE Name=gpu Type=$GPU_TYPE File=$DIR/gpu[0-$((GPUS - 1))]" >"$(dirname "$CONF")/gres.conf"
}

# Runs a check every 0.2 s until it succeeds (status 0); status 1 when the seconds run out or the check gives up
# (its status 2).
wait_until() {
  local seconds=$1 status
  shift
  for _ in $(seq $((seconds * 5))); do
    status=0
    "$@" || status=$?
    [ $status -eq 0 ] && return 0
    [ $status -eq 2 ] && return 1
    sleep 0.2
  done
  return 1
}

# Status 2 once the daemon has written its pid file and died: no use waiting for it.
died() {
  [ -s "$2" ] && ! alive "$1" "$2"
}

controller_up() {
  died slurmctld "$DIR/slurmctld.pid" && return 2
  scontrol ping >/dev/null 2>&1
}

node_ready() {
  local state
  died slurmd "$DIR/slurmd.pid" && return 2
  state=$(sinfo -h -N -n "$NODE" -o %T 2>/dev/null | head -n 1) || return 1  # a line per partition
  case "$state" in
    idle | mixed | allocated | completing) return 0 ;;
    drained | draining | down | inval) scontrol update nodename="$NODE" state=resume >/dev/null 2>&1 || true ;;
  esac
  return 1
}

need_root() {
  [ "$(id -u)" -eq 0 ] || fail "needs root: slurmd starts every job as its user (run: sudo $0 $1)"
}

start() {
  need_root start
  mkdir -p "$DIR"
  if running; then
    echo "slurm: already running (configuration: $CONF, logs: $DIR)"
    return
  fi
  if [ -e "$CONF" ] && [ "$(head -n 1 "$CONF")" != "$MARK" ]; then
    fail "$CONF was not written by this script: this machine has a SLURM of its own (use it, docs/slurm.md)"
  fi
  install
  configure
  if ! alive munged "$DIR/munge/munged.pid"; then
    munged --key-file="$DIR/munge/munge.key" --socket="$DIR/munge/munge.socket" --pid-file="$DIR/munge/munged.pid" \
      --log-file="$DIR/munge/munged.log" --seed-file="$DIR/munge/munged.seed" ||
      fail "munged did not start: $(last_error "$DIR/munge/munged.log")"
  fi
  if ! alive slurmctld "$DIR/slurmctld.pid"; then
    # -c: a fresh controller forgets the jobs of an earlier session
    slurmctld -c || fail "slurmctld did not start: $(last_error "$DIR/slurmctld.log")"
  fi
  wait_until 30 controller_up ||
    fail "slurmctld does not answer: $(last_error "$DIR/slurmctld.log")"
  if ! alive slurmd "$DIR/slurmd.pid"; then
    slurmd || fail "slurmd did not start: $(last_error "$DIR/slurmd.log")"
  fi
  wait_until 30 node_ready ||
    fail "node $NODE is not ready: $(last_error "$DIR/slurmctld.log" "$DIR/slurmd.log")"
  echo "slurm: running (configuration: $CONF, logs: $DIR)"
}

gone() {
  ! kill -0 "$1" 2>/dev/null
}

no_jobs_left() {
  [ -z "$(squeue -h -t pending,running,completing,configuring 2>/dev/null)" ]
}

stop_daemon() {
  local name=$1 pidfile=$2
  alive "$name" "$pidfile" || return 0
  local pid
  pid=$(cat "$pidfile")
  kill "$pid"
  wait_until 15 gone "$pid" || kill -9 "$pid" 2>/dev/null || true
  rm -f "$pidfile"
}

stop() {
  need_root stop
  if alive slurmctld "$DIR/slurmctld.pid"; then
    scancel --full --user="$(id -un)" 2>/dev/null || true
    wait_until 30 no_jobs_left ||
      echo "slurm: jobs still running after scancel; stopping anyway" >&2
  fi
  stop_daemon slurmd "$DIR/slurmd.pid"
  stop_daemon slurmctld "$DIR/slurmctld.pid"
  stop_daemon munged "$DIR/munge/munged.pid"
  echo "slurm: stopped"
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status)
    if running; then echo "slurm: running (configuration: $CONF, logs: $DIR)"; else echo "slurm: not running"; exit 1; fi
    ;;
  *) fail "usage: $0 start|status|stop" ;;
esac
