#!/usr/bin/env bash
# Start a single-node Slurm "cluster" on this machine: munged + slurmctld + slurmd, all on localhost.
#
# Used by tests/slurm/test_slurm.py (CI) and by hand:
#     sudo tests/slurm/start_cluster.sh        # prints the state directory and the PIDs it started
#     sinfo; sbatch --wrap 'hostname'; ...
#     sudo tests/slurm/stop_cluster.sh         # stops exactly those PIDs
#
# What it does (idempotent: a second call while the cluster is up only checks it and exits 0):
#   1. installs slurmctld slurmd slurm-client munge from the distribution's packages when a command is missing
#      (apt-get, non-interactive; services are NOT started by the packages: a temporary policy-rc.d forbids it
#      when the machine has none);
#   2. writes a munge key and the daemons' state under $CTSPLAT_SLURM_DIR (default /tmp/ctsplat-slurm) and
#      /etc/slurm/slurm.conf (+ gres.conf) for one node named $(hostname -s): CPUs = nproc, RealMemory = 90 %
#      of MemTotal, no cgroups (proctrack/linuxproc, task/none), no accounting (accounting_storage/none, so
#      there is no slurmdbd and `sacct` does not work: use `squeue` for job status), MinJobAge = 3600 s so that
#      finished jobs stay visible to `squeue --states=all`, and $CTSPLAT_SLURM_GPUS fake `gpu` GRES
#      (default nproc, one fake device file each under the state directory; 0 disables them) so jobs asking for `--gpus=1` can be scheduled (no real device behind it);
#      /etc/slurm/slurm.conf is written only when absent or written by this script before (marker line);
#      it has to live there because the Snakemake jobstep plugin drops SLURM_CONF for its nested `srun`;
#   3. starts munged (own socket and key under the state directory), slurmctld and slurmd as root, each as a
#      daemon with a pid file, records "name pid" lines in $CTSPLAT_SLURM_DIR/pids;
#   4. waits (up to $CTSPLAT_SLURM_TIMEOUT seconds, default 90) until `sinfo` reports the node idle.
#
# Needs root and Linux. Environment: CTSPLAT_SLURM_DIR, CTSPLAT_SLURM_GPUS, CTSPLAT_SLURM_TIMEOUT,
# CTSPLAT_SLURMCTLD_PORT (6817), CTSPLAT_SLURMD_PORT (6818).
# Exit status: 0 cluster up; 1 failure (message on stderr, daemon logs under the state directory);
# 3 the packages could not be installed (e.g. no network); 4 a Slurm set-up or daemon not ours is in the way.
set -euo pipefail

STATE_DIR=${CTSPLAT_SLURM_DIR:-/tmp/ctsplat-slurm}
GPUS=${CTSPLAT_SLURM_GPUS:-$(nproc)}
TIMEOUT=${CTSPLAT_SLURM_TIMEOUT:-90}
CTLD_PORT=${CTSPLAT_SLURMCTLD_PORT:-6817}
SLURMD_PORT=${CTSPLAT_SLURMD_PORT:-6818}
CONF_DIR=/etc/slurm
CONF=$CONF_DIR/slurm.conf
MARKER="# written by ctsplat tests/slurm/start_cluster.sh"
PKGS=(slurmctld slurmd slurm-client munge)

die() { echo "start_cluster.sh: error: $*" >&2; exit "${DIE_CODE:-1}"; }
log() { echo "start_cluster.sh: $*" >&2; }

[[ $(uname -s) == Linux ]] || die "needs Linux (found $(uname -s))"
[[ $(id -u) == 0 ]] || die "needs root (run it with sudo): it installs packages, writes $CONF and starts daemons"

# --- 1. packages ----------------------------------------------------------------------------------------
missing=()
for cmd in munged slurmctld slurmd sbatch squeue sinfo scontrol srun; do
    command -v "$cmd" >/dev/null 2>&1 || PATH="$PATH:/usr/sbin:/sbin" command -v "$cmd" >/dev/null 2>&1 || missing+=("$cmd")
done
export PATH="$PATH:/usr/sbin:/sbin"
if ((${#missing[@]})); then
    command -v apt-get >/dev/null 2>&1 || DIE_CODE=3 die "missing ${missing[*]} and no apt-get to install ${PKGS[*]}; install Slurm and munge by hand"
    log "installing ${PKGS[*]} (missing: ${missing[*]})"
    # Keep the packages' maintainer scripts from starting their own munged/slurmd: we start ours below.
    policy_created=0
    if [[ ! -e /usr/sbin/policy-rc.d ]]; then
        printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d
        chmod 755 /usr/sbin/policy-rc.d
        policy_created=1
    fi
    export DEBIAN_FRONTEND=noninteractive
    apt_log=$(mktemp)
    rc=0
    {
        # `apt-get update` only when the package lists do not know the packages yet (fresh CI images).
        # A failed install with lists present may mean stale lists: update once and retry.
        if ! apt-cache show slurmctld >/dev/null 2>&1; then apt-get update -q; fi
        apt-get install -y -q --no-install-recommends "${PKGS[@]}" \
            || { apt-get update -q && apt-get install -y -q --no-install-recommends "${PKGS[@]}"; }
    } >"$apt_log" 2>&1 </dev/null || rc=$?
    ((policy_created)) && rm -f /usr/sbin/policy-rc.d
    if ((rc)); then
        tail -20 "$apt_log" >&2
        DIE_CODE=3 die "apt-get install ${PKGS[*]} failed (exit $rc); full log: $apt_log"
    fi
    rm -f "$apt_log"
fi

# --- helpers --------------------------------------------------------------------------------------------
# alive NAME PID: the process PID exists and is the daemon NAME (guards against recycled PIDs).
# A zombie (killed, not yet reaped) is not alive.
alive() {
    [[ -n ${2:-} && -r /proc/$2/comm ]] && [[ $(cat "/proc/$2/comm" 2>/dev/null) == "$1" ]] \
        && ! grep -qE '^State:[[:space:]]+Z' "/proc/$2/status" 2>/dev/null
}
node_state() { sinfo -h -N -n "$NODE" -o '%T' 2>/dev/null | head -1; }

NODE=$(hostname -s)
[[ -n $NODE ]] || die "hostname -s is empty; set a hostname first"

# Already up (started by this script, all three PIDs alive and the node answers)? Nothing to do.
if [[ -f $STATE_DIR/pids ]]; then
    all_alive=1
    while read -r name pid; do alive "$name" "$pid" || all_alive=0; done <"$STATE_DIR/pids"
    if ((all_alive)) && [[ $(node_state) =~ ^(idle|mixed|allocated) ]]; then
        log "cluster already running (state $STATE_DIR, node $NODE $(node_state))"
        cat "$STATE_DIR/pids"
        exit 0
    fi
    log "stale or partial cluster in $STATE_DIR: stopping what is left and starting again"
    "$(dirname "$0")/stop_cluster.sh" || true
fi

# Refuse to clobber a real Slurm set-up or fight a daemon that is not ours.
if [[ -e $CONF ]] && ! grep -qF "$MARKER" "$CONF"; then
    DIE_CODE=4 die "$CONF exists and was not written by this script; refusing to overwrite a real Slurm configuration"
fi
for d in munged slurmctld slurmd; do
    for pid in $(pgrep -x "$d" 2>/dev/null); do
        if alive "$d" "$pid"; then
            DIE_CODE=4 die "a $d process not started by this script is running (pid $pid); stop it first"
        fi
    done
done

# --- 2. configuration -----------------------------------------------------------------------------------
mkdir -p "$STATE_DIR"/{munge,ctld,spool,log,run} "$CONF_DIR"
chmod 700 "$STATE_DIR/munge"
rm -f "$STATE_DIR/pids"

KEY=$STATE_DIR/munge/munge.key
if [[ ! -s $KEY ]]; then
    dd if=/dev/urandom of="$KEY" bs=1024 count=1 status=none
fi
chmod 400 "$KEY"
SOCKET=$STATE_DIR/munge/munge.socket.2

CPUS=$(nproc)
mem_total_mb=$(awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo)
REAL_MEM=$((mem_total_mb * 9 / 10))

[[ $GPUS =~ ^[0-9]+$ ]] || die "CTSPLAT_SLURM_GPUS must be a whole number of fake gpus (0 disables them), got '$GPUS'"
gres_node=""
gres_types=""
if ((GPUS > 0)); then
    gres_node=" Gres=gpu:$GPUS"
    gres_types="GresTypes=gpu"
fi

tmp_conf=$(mktemp "$CONF_DIR/.slurm.conf.XXXXXX")
cat >"$tmp_conf" <<EOF
$MARKER
# Single-node test cluster on localhost ($NODE). State: $STATE_DIR. Stop with tests/slurm/stop_cluster.sh.
ClusterName=ctsplat
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$SOCKET
StateSaveLocation=$STATE_DIR/ctld
SlurmdSpoolDir=$STATE_DIR/spool
SlurmctldPidFile=$STATE_DIR/run/slurmctld.pid
SlurmdPidFile=$STATE_DIR/run/slurmd.pid
SlurmctldLogFile=$STATE_DIR/log/slurmctld.log
SlurmdLogFile=$STATE_DIR/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
# No cgroups (CI containers rarely delegate them), no accounting database.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SchedulerType=sched/builtin
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
# Keep finished jobs in slurmctld for 1 h: the plugin polls them with squeue, the test reads them afterwards.
MinJobAge=3600
KillWait=5
MailProg=/bin/true
InactiveLimit=0
SlurmctldTimeout=60
SlurmdTimeout=60
$gres_types
NodeName=$NODE NodeAddr=127.0.0.1 NodeHostname=$NODE CPUs=$CPUS RealMemory=$REAL_MEM$gres_node State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
chmod 644 "$tmp_conf"
mv -f "$tmp_conf" "$CONF"
if ((GPUS > 0)); then
    # Fake devices: character devices with /dev/null's numbers (1:3) where mknod is allowed, else plain files
    # (slurmd then logs "not a valid character or block device" but counts them); task/none confines nothing.
    mkdir -p "$STATE_DIR/gpu"
    {
        echo "$MARKER"
        for ((g = 0; g < GPUS; g++)); do
            if [[ ! -e $STATE_DIR/gpu/fake$g ]]; then
                mknod -m 666 "$STATE_DIR/gpu/fake$g" c 1 3 2>/dev/null || : >"$STATE_DIR/gpu/fake$g"
            fi
            echo "NodeName=$NODE Name=gpu File=$STATE_DIR/gpu/fake$g"
        done
    } >"$CONF_DIR/gres.conf"
elif [[ -e $CONF_DIR/gres.conf ]] && grep -qF "$MARKER" "$CONF_DIR/gres.conf"; then
    rm -f "$CONF_DIR/gres.conf"
fi
# A fresh controller state: jobs from an earlier cluster are forgotten.
rm -rf "${STATE_DIR:?}/ctld/"* "${STATE_DIR:?}/spool/"*

# --- 3. daemons -----------------------------------------------------------------------------------------
record() { echo "$1 $2" >>"$STATE_DIR/pids"; }
wait_pidfile() {  # wait_pidfile NAME FILE: the daemon NAME wrote FILE and runs
    local i pid
    for ((i = 0; i < 100; i++)); do
        if [[ -s $2 ]]; then
            pid=$(tr -dc '0-9' <"$2")
            if alive "$1" "$pid"; then echo "$pid"; return 0; fi
        fi
        sleep 0.2
    done
    return 1
}

rm -f "$STATE_DIR"/run/*.pid "$SOCKET"
munged --force --key-file="$KEY" --socket="$SOCKET" --pid-file="$STATE_DIR/run/munged.pid" \
    --log-file="$STATE_DIR/log/munged.log" --seed-file="$STATE_DIR/munge/munged.seed" </dev/null \
    || die "munged failed to start; see $STATE_DIR/log/munged.log"
pid=$(wait_pidfile munged "$STATE_DIR/run/munged.pid") || die "munged did not come up; see $STATE_DIR/log/munged.log"
record munged "$pid"
# Check that a credential round-trips through our munged.
munge -n --socket="$SOCKET" | unmunge --socket="$SOCKET" >/dev/null \
    || die "munge credential check failed; see $STATE_DIR/log/munged.log"

slurmctld -f "$CONF" </dev/null >/dev/null 2>&1 || die "slurmctld failed to start; see $STATE_DIR/log/slurmctld.log"
pid=$(wait_pidfile slurmctld "$STATE_DIR/run/slurmctld.pid") \
    || die "slurmctld did not come up; see $STATE_DIR/log/slurmctld.log"
record slurmctld "$pid"

slurmd -f "$CONF" -N "$NODE" </dev/null >/dev/null 2>&1 || die "slurmd failed to start; see $STATE_DIR/log/slurmd.log"
pid=$(wait_pidfile slurmd "$STATE_DIR/run/slurmd.pid") || die "slurmd did not come up; see $STATE_DIR/log/slurmd.log"
record slurmd "$pid"

# --- 4. wait for the node -------------------------------------------------------------------------------
deadline=$((SECONDS + TIMEOUT))
resumed=0
state=""
while ((SECONDS < deadline)); do
    state=$(node_state || true)
    case $state in
        idle*) break ;;
        *inval*)
            break ;;
        down* | drain* | fail*)
            if ((!resumed)); then
                scontrol update NodeName="$NODE" State=RESUME >/dev/null 2>&1 || true
                resumed=1
            fi
            ;;
    esac
    sleep 0.5
done
if [[ $state != idle* ]]; then
    scontrol show node "$NODE" >&2 || true
    tail -n 5 "$STATE_DIR/log/slurmctld.log" "$STATE_DIR/log/slurmd.log" >&2 || true
    die "node $NODE not idle after ${TIMEOUT}s (state '${state:-no answer}'); stop with $(dirname "$0")/stop_cluster.sh"
fi
log "cluster up: node $NODE idle, $CPUS CPUs, ${REAL_MEM} MB, gpu gres $GPUS; state $STATE_DIR"
cat "$STATE_DIR/pids"
