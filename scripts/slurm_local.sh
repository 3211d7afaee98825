#!/usr/bin/env bash
# A real single-node SLURM cluster on this Debian machine, from Debian's packages, for testing the
# pipeline's SLURM profile (profiles/slurm, tests/workflow/test_slurm.py). Run as root.
#
#   bash scripts/slurm_local.sh          # install (first run), configure, start; wait for `srun hostname`
#   bash scripts/slurm_local.sh stop     # stop the daemons this script started
#
# What it sets up (idempotent: a second run with everything up returns in about a second):
#   - packages: slurmctld, slurmd, slurmdbd, slurm-client, munge, mariadb-server
#   - munge with Debian's key; MariaDB (the package's data directory) with the database
#     slurm_acct_db and its user; slurmdbd (accounting: Snakemake's SLURM plugin polls `sacct`)
#   - /etc/slurm/slurm.conf with this node's real CPU count and memory (`slurmd -C`), one partition
#     `debug` (default), cons_tres scheduling of cores and memory, accounting through slurmdbd
#   - state, spool, pid and log files under $RECON_SLURM_DIR (default /tmp/recon-slurm)
#   - cluster `recon`, account `recon`, and the calling user in it as its default account
# The machine may have no systemd (containers): the daemons are started directly, in the background.
# Logs: $RECON_SLURM_DIR/log/{slurmctld,slurmd,slurmdbd,mariadb}.log, /var/log/munge/munged.log
set -euo pipefail

dir=${RECON_SLURM_DIR:-/tmp/recon-slurm}
cluster=recon
account=recon
partition=debug
user=$(id -un)
log() { printf '[slurm_local] %s\n' "$*" >&2; }

if [ "$(id -u)" -ne 0 ]; then
  log "run as root (installs packages, starts munged/mariadbd/slurmdbd/slurmctld/slurmd)"
  exit 1
fi

# Start a daemon in the background unless its pid file names a live process with the same name.
running() {  # pidfile name
  [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null && grep -q "$2" "/proc/$(cat "$1")/comm" 2>/dev/null
}

stop_all() {
  local name pidfile pid
  for name in slurmd slurmctld slurmdbd; do
    pidfile=$dir/run/$name.pid
    if running "$pidfile" "$name"; then
      pid=$(cat "$pidfile")
      log "stopping $name ($pid)"
      kill "$pid"
      for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    fi
  done
}

if [ "${1:-}" = "stop" ]; then
  stop_all
  exit 0
fi

# ---- Packages ----
need=()
for pair in slurmctld:slurmctld slurmd:slurmd slurmdbd:slurmdbd sbatch:slurm-client \
            munged:munge mariadbd:mariadb-server; do
  command -v "${pair%%:*}" >/dev/null 2>&1 || [ -x "/usr/sbin/${pair%%:*}" ] || need+=("${pair#*:}")
done
if [ ${#need[@]} -gt 0 ]; then
  log "installing ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
export PATH="/usr/sbin:$PATH"

mkdir -p "$dir"/{state,spool,run,log}
chown slurm:slurm "$dir/state" "$dir/log" "$dir/run"
chmod 755 "$dir" "$dir/run" "$dir/log"

# ---- munge ----
[ -s /etc/munge/munge.key ] || { log "creating /etc/munge/munge.key"; mungekey --create --force; }
chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
install -d -o munge -g munge -m 755 /run/munge /var/log/munge /var/lib/munge
if ! munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1; then
  log "starting munged"
  runuser -u munge -- /usr/sbin/munged --force
  for _ in $(seq 50); do munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.1; done
  munge -n </dev/null | unmunge >/dev/null || { log "munged did not come up: /var/log/munge/munged.log"; exit 1; }
fi

# ---- MariaDB (accounting database) ----
install -d -o mysql -g mysql -m 755 /run/mysqld
if ! mariadb-admin --protocol=socket ping >/dev/null 2>&1; then
  log "starting mariadbd"
  [ -d /var/lib/mysql/mysql ] || mariadb-install-db --user=mysql --datadir=/var/lib/mysql >/dev/null
  setsid /usr/sbin/mariadbd --user=mysql --datadir=/var/lib/mysql --socket=/run/mysqld/mysqld.sock \
    --bind-address=127.0.0.1 --innodb-buffer-pool-size=64M --innodb-lock-wait-timeout=900 \
    >"$dir/log/mariadb.log" 2>&1 </dev/null &
  for _ in $(seq 100); do mariadb-admin --protocol=socket ping >/dev/null 2>&1 && break; sleep 0.2; done
  mariadb-admin --protocol=socket ping >/dev/null || { log "mariadbd did not come up: $dir/log/mariadb.log"; exit 1; }
fi
dbpass=recon-slurmdbd   # the database listens on 127.0.0.1 only
mariadb --protocol=socket -e "
  CREATE DATABASE IF NOT EXISTS slurm_acct_db;
  CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY '$dbpass';
  GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';"

# ---- Configuration files (rewritten only when they change; a change restarts the daemons) ----
node=$(hostname -s)
# `slurmd -C` prints this node's real hardware: CPUs, Boards, Sockets, Cores, Threads, RealMemory.
hw=$(slurmd -C | head -1 | sed -e 's/^NodeName=[^ ]* //')
changed=0
write_if_changed() {  # path mode owner  (content on stdin)
  local tmp
  tmp=$(mktemp)
  cat >"$tmp"
  if [ -f "$1" ] && cmp -s "$tmp" "$1"; then rm -f "$tmp"; return; fi
  install -m "$2" -o "$3" -g "$3" "$tmp" "$1"
  rm -f "$tmp"
  changed=1
  log "wrote $1"
}
mkdir -p /etc/slurm
write_if_changed /etc/slurm/slurm.conf 644 root <<EOF
# Written by recon's scripts/slurm_local.sh: a single-node test cluster.
ClusterName=$cluster
SlurmctldHost=$node
AuthType=auth/munge
SlurmUser=slurm
SlurmdUser=root
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/run/slurmctld.pid
SlurmdPidFile=$dir/run/slurmd.pid
SlurmctldLogFile=$dir/log/slurmctld.log
SlurmdLogFile=$dir/log/slurmd.log
# No cgroup hierarchy to manage in a container: track processes by their parents.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=5
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStorageEnforce=associations
# sacct shows the executor plugin's --comment (rule_<name>_wildcards_<values>) per job.
AccountingStoreFlags=job_comment
JobCompType=jobcomp/none
# A job past its time limit gets SIGTERM, then SIGKILL after KillWait seconds.
KillWait=10
MinJobAge=300
ReturnToService=2
SchedulerParameters=defer_batch
NodeName=$node $hw State=UNKNOWN
PartitionName=$partition Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
write_if_changed /etc/slurm/slurmdbd.conf 600 slurm <<EOF
# Written by recon's scripts/slurm_local.sh
AuthType=auth/munge
DbdHost=localhost
SlurmUser=slurm
PidFile=$dir/run/slurmdbd.pid
LogFile=$dir/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=$dbpass
StorageLoc=slurm_acct_db
EOF
[ $changed -eq 1 ] && stop_all

# ---- Daemons ----
if ! running "$dir/run/slurmdbd.pid" slurmdbd; then
  log "starting slurmdbd"
  slurmdbd
  for _ in $(seq 100); do sacctmgr -n list cluster >/dev/null 2>&1 && break; sleep 0.2; done
fi
sacctmgr -n list cluster >/dev/null || { log "slurmdbd did not answer: $dir/log/slurmdbd.log"; exit 1; }
# The cluster, the account and the user before slurmctld registers (sacctmgr -i: no prompt).
sacctmgr -n -P list cluster format=cluster | grep -qx "$cluster" || sacctmgr -i add cluster "$cluster" >/dev/null
sacctmgr -n -P list account format=account | grep -qx "$account" || \
  sacctmgr -i add account "$account" Cluster="$cluster" Description="recon pipeline" Organization=recon >/dev/null
sacctmgr -n -P list assoc format=user,account where user="$user" account="$account" | grep -q . || \
  sacctmgr -i add user "$user" Account="$account" Cluster="$cluster" >/dev/null
[ "$(sacctmgr -n -P list user "$user" format=defaultaccount)" = "$account" ] || \
  sacctmgr -i modify user "$user" set DefaultAccount="$account" >/dev/null

if ! running "$dir/run/slurmctld.pid" slurmctld; then
  log "starting slurmctld"
  slurmctld
fi
if ! running "$dir/run/slurmd.pid" slurmd; then
  log "starting slurmd"
  slurmd
fi

# ---- Wait until a job runs ----
for i in $(seq 60); do
  state=$(sinfo -h -n "$node" -o %T 2>/dev/null || true)
  case "$state" in
    down*|drain*) scontrol update nodename="$node" state=resume >/dev/null 2>&1 || true ;;
  esac
  if out=$(timeout 20 srun -Q -N1 -n1 -t 1 hostname 2>/dev/null) && [ "$out" = "$node" ]; then
    log "ready: node $node ($hw), partition $partition, account $account, user $user (${i} tries)"
    exit 0
  fi
  sleep 1
done
log "srun hostname did not work within a minute: see $dir/log/slurmctld.log and slurmd.log"
sinfo >&2 || true
exit 1
