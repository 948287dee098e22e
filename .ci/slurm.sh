#!/usr/bin/env bash
# CI: the test study on a real one-node SLURM cluster through profiles/slurm, after .ci/run's local run.
# Installs Debian's slurm-wlm and munge, starts munged, slurmctld and slurmd (no accounting database, so
# the profile's squeue status command is what keeps the run from hanging), runs config/test.yaml in a copy
# of the repository, and compares every voi.csv and bins.csv it writes with the local run's file at the
# same path under results/. Every daemon and job it started is stopped on exit. Runs as root.
# SNAKEMAKE=/path/to/snakemake runs another environment's Snakemake (default: the repository's .venv).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
snakemake="${SNAKEMAKE:-$repo/.venv/bin/snakemake}"
python="$(dirname "$snakemake")/python"
SECONDS=0

export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq slurm-wlm munge > /dev/null
echo "slurm packages installed: ${SECONDS} s"

tmp="$(mktemp -d /tmp/deeptissue-slurm.XXXXXX)"
chmod 755 "$tmp"
pids=()
wrote_conf=""
stop() {
    local status=$?
    if [ "$status" -ne 0 ]; then  # what the daemons and the cluster run said
        tail -n 30 "$tmp"/log/* "$tmp"/repo/.snakemake/log/*.log 2> /dev/null || true
    fi
    scancel --full --quiet 2> /dev/null || true
    for _ in $(seq 20); do squeue -h 2> /dev/null | grep -q . || break; sleep 0.5; done
    for ((i = ${#pids[@]} - 1; i >= 0; i--)); do kill "${pids[i]}" 2> /dev/null || true; done
    for pid in "${pids[@]}"; do wait "$pid" 2> /dev/null || true; done
    rm -rf "$tmp"
    if [ -n "$wrote_conf" ]; then rm -f /etc/slurm/slurm.conf; fi
    return "$status"
}
trap stop EXIT

# munge, on a socket of its own: slurm.conf's AuthInfo points the daemons and commands at it
mkdir -p "$tmp/munge" "$tmp/state" "$tmp/spool" "$tmp/log"
chown munge:munge "$tmp/munge"
chmod 755 "$tmp/munge"
test -s /etc/munge/munge.key || mungekey --create --keyfile=/etc/munge/munge.key
setpriv --reuid=munge --regid=munge --init-groups /usr/sbin/munged --foreground --force \
    --socket="$tmp/munge/socket" --pid-file="$tmp/munge/munged.pid" --seed-file="$tmp/munge/seed" \
    --log-file="$tmp/munge/munged.log" > "$tmp/log/munged.out" 2>&1 &
pids+=($!)

# one node with this machine's CPUs and its memory less 1 GB, one partition, no accounting, no cgroups;
# finished jobs stay listed by squeue for an hour, so the table below shows every job of the run
node="$(hostname -s)"
cpus="$(nproc)"
mem_mb="$(free -m | awk '/^Mem:/ {print $2 - 1024}')"
# in the default place, where the srun inside each job finds it too
if [ -e /etc/slurm/slurm.conf ]; then
    echo "/etc/slurm/slurm.conf exists: this machine has a cluster of its own" >&2
    exit 1
fi
mkdir -p /etc/slurm
wrote_conf=1
cat > /etc/slurm/slurm.conf << CONF
ClusterName=ci
SlurmctldHost=$node
AuthType=auth/munge
AuthInfo=socket=$tmp/munge/socket
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/log/slurmctld.log
SlurmdLogFile=$tmp/log/slurmd.log
MailProg=/bin/true
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SwitchType=switch/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MinJobAge=3600
NodeName=$node CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=ci Nodes=$node Default=YES MaxTime=INFINITE State=UP
CONF
for _ in $(seq 50); do test -S "$tmp/munge/socket" && break; sleep 0.2; done
/usr/sbin/slurmctld -D -i > "$tmp/log/slurmctld.out" 2>&1 &
pids+=($!)
/usr/sbin/slurmd -D > "$tmp/log/slurmd.out" 2>&1 &
pids+=($!)
for _ in $(seq 60); do sinfo -h -o %t 2> /dev/null | grep -qx idle && break; sleep 1; done
if ! sinfo -h -o %t | grep -qx idle; then
    sinfo -N -l || true
    cat "$tmp"/log/*
    exit 1
fi
echo "one-node cluster up ($cpus CPUs, $mem_mb MB): ${SECONDS} s"

# the test study through the profile, in a copy of the repository (its own results/ and .snakemake/)
mkdir "$tmp/repo"
tar -C "$repo" --exclude=./.git --exclude=./.venv --exclude=./results --exclude=./.snakemake -cf - . \
    | tar -C "$tmp/repo" -xf -
start=$SECONDS
(cd "$tmp/repo" && "$snakemake" all --profile profiles/slurm --configfile config/test.yaml --quiet \
    --slurm-init-seconds-before-status-checks 2)
echo "config/test.yaml through profiles/slurm: $((SECONDS - start)) s; its jobs:"
squeue -t all -h -o "%.10T %.19S %.19e %.8M  %k" | sort -k2

# the same values as the local run: every column but how the solve went (Newton iterations, increments,
# attempts, penetration, timings) to 1e-6 relative, the accuracy of a solve converged to a 1e-6 residual
"$python" - "$tmp/repo/results" "$repo/results" << 'PY'
import sys
from pathlib import Path

import numpy as np
import pandas as pd

cluster, local = Path(sys.argv[1]), Path(sys.argv[2])
paths = sorted(p.relative_to(cluster) for name in ("voi.csv", "bins.csv") for p in cluster.rglob(name))
assert {p.name for p in paths} == {"voi.csv", "bins.csv"}, f"the cluster run wrote {paths}"
run_dependent = ("newton_iterations", "increments", "attempts", "max_penetration_mm", "max_penetration_rel")
for rel in paths:
    a, b = pd.read_csv(cluster / rel), pd.read_csv(local / rel)
    assert list(a.columns) == list(b.columns) and len(a) == len(b), f"{rel}: other columns or rows"
    for col in a.columns:
        if col in run_dependent or col.endswith("_s"):
            continue
        x, y = a[col], b[col]
        if pd.api.types.is_numeric_dtype(x) and not pd.api.types.is_bool_dtype(x):
            ok = np.allclose(x, y, rtol=1e-6, atol=1e-9, equal_nan=True)
        else:
            ok = x.fillna("").astype(str).equals(y.fillna("").astype(str))
        assert ok, f"{rel}, column {col}: cluster {x.tolist()} != local {y.tolist()}"
    print(f"{rel}: {len(a)} rows equal to the local run's")
PY
echo "SLURM step: ${SECONDS} s"
