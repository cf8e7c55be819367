#!/usr/bin/env bash
# What the encode-cluster lab scripts (cluster-loopback.sh, device-cluster.sh) share: the cluster's
# secret file and its hosts file on loopback. Sourced, not run.

# cluster_secret DIR: DIR/secret, 32 random bytes in base64, readable by the owner only.
cluster_secret() { (umask 077; head -c 32 /dev/urandom | base64 > "$1/secret"); }

# cluster_hosts DIR N: DIR/hosts, N lines `127.0.0.1:PORT`, each PORT a loopback port that was free
# when picked (the kernel's pick for a bound socket, released before the processes start).
cluster_hosts() {
  local ports p
  ports=$(python3 -c "import socket
s=[socket.socket() for _ in range($2)]
[x.bind(('127.0.0.1',0)) for x in s]
print(' '.join(str(x.getsockname()[1]) for x in s))")
  : > "$1/hosts"; for p in $ports; do echo "127.0.0.1:$p" >> "$1/hosts"; done
}
