#!/usr/bin/env bash
# Stop the single-node Slurm cluster started by tests/slurm/start_cluster.sh.
#
# Cancels the jobs still queued or running on it, then stops exactly the daemons listed in
# $CTSPLAT_SLURM_DIR/pids (default /tmp/ctsplat-slurm/pids) -- each PID only while /proc says it is still that
# daemon -- with SIGTERM, then SIGKILL after 15 s. Removes /etc/slurm/slurm.conf and gres.conf only when
# start_cluster.sh wrote them (marker line). Logs stay under the state directory. Idempotent: exit 0 when
# nothing is running.
set -uo pipefail

STATE_DIR=${CTSPLAT_SLURM_DIR:-/tmp/ctsplat-slurm}
CONF_DIR=/etc/slurm
MARKER="# written by ctsplat tests/slurm/start_cluster.sh"
export PATH="$PATH:/usr/sbin:/sbin"

log() { echo "stop_cluster.sh: $*" >&2; }
alive() {  # alive NAME PID: PID is the daemon NAME and not a zombie
    [[ -n ${2:-} && -r /proc/$2/comm ]] && [[ $(cat "/proc/$2/comm" 2>/dev/null) == "$1" ]] \
        && ! grep -qE '^State:[[:space:]]+Z' "/proc/$2/status" 2>/dev/null
}

if [[ ! -f $STATE_DIR/pids ]]; then
    log "no $STATE_DIR/pids: nothing to stop"
    exit 0
fi

declare -A pid_of=()
while read -r name pid; do
    [[ -n ${name:-} ]] && pid_of[$name]=$pid
done <"$STATE_DIR/pids"

# Jobs first, while slurmctld still answers, so no slurmstepd or job process outlives the cluster.
if alive slurmctld "${pid_of[slurmctld]:-}" && command -v scancel >/dev/null 2>&1; then
    scancel --state=PENDING,RUNNING,SUSPENDED --full >/dev/null 2>&1 || scancel --full >/dev/null 2>&1 || true
    for ((i = 0; i < 30; i++)); do
        [[ -z $(squeue -h -t RUNNING,COMPLETING,PENDING -o %i 2>/dev/null) ]] && break
        sleep 0.5
    done
fi

# Daemons in reverse start order: slurmd, slurmctld, munged.
for name in slurmd slurmctld munged; do
    pid=${pid_of[$name]:-}
    if alive "$name" "$pid"; then
        kill -TERM "$pid" 2>/dev/null || true
        for ((i = 0; i < 30; i++)); do
            alive "$name" "$pid" || break
            sleep 0.5
        done
        if alive "$name" "$pid"; then
            log "$name ($pid) ignored SIGTERM; sending SIGKILL"
            kill -KILL "$pid" 2>/dev/null || true
        fi
        log "stopped $name ($pid)"
    elif [[ -n $pid ]]; then
        log "$name ($pid) was not running"
    fi
done
rm -f "$STATE_DIR/pids"

for f in "$CONF_DIR/slurm.conf" "$CONF_DIR/gres.conf"; do
    if [[ -f $f ]] && grep -qF "$MARKER" "$f"; then rm -f "$f"; fi
done
exit 0
