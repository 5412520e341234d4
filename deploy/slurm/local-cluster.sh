#!/usr/bin/env bash
# Starts or stops a one-host Slurm cluster (slurmctld + slurmd on this machine, munge for
# authentication) whose config and state live in DIR, from deploy/slurm/slurm.conf.in. Needs
# root and Debian's slurm-wlm and munge. Then `SLURM_CONF=DIR/slurm.conf sbatch …`.
#
#   deploy/slurm/local-cluster.sh start DIR     # prints the SLURM_CONF to export
#   deploy/slurm/local-cluster.sh stop DIR
set -euo pipefail
cmd=${1:?usage: local-cluster.sh start|stop DIR}
dir=${2:?usage: local-cluster.sh start|stop DIR}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$dir"
dir=$(cd "$dir" && pwd)
conf="$dir/slurm.conf"
case "$cmd" in
start)
  mkdir -p "$dir/state" "$dir/spool"
  # munge: the machine's daemon if one answers, else one of our own (with the package's key).
  if ! munge -n </dev/null >/dev/null 2>&1; then
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    munged --force --pid-file="$dir/munged.pid"
    for _ in $(seq 50); do munge -n </dev/null >/dev/null 2>&1 && break; sleep 0.1; done
  fi
  port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
  sed -e "s|@HOST@|$(hostname -s)|g" -e "s|@DIR@|$dir|g" \
      -e "s|@CTLD_PORT@|$(port)|" -e "s|@D_PORT@|$(port)|" "$here/slurm.conf.in" > "$conf"
  slurmctld -f "$conf"
  slurmd -f "$conf"
  for _ in $(seq 100); do
    if SLURM_CONF="$conf" sinfo -h -o %T 2>/dev/null | grep -q idle; then
      echo "SLURM_CONF=$conf"
      exit 0
    fi
    sleep 0.2
  done
  echo "local-cluster.sh: the node did not become idle; see $dir/slurmctld.log and $dir/slurmd.log" >&2
  exit 1
  ;;
stop)
  for d in slurmd slurmctld munged; do
    if [ -f "$dir/$d.pid" ]; then
      kill "$(cat "$dir/$d.pid")" 2>/dev/null || true
      rm -f "$dir/$d.pid"
    fi
  done
  ;;
*)
  echo "usage: local-cluster.sh start|stop DIR" >&2
  exit 2
  ;;
esac
