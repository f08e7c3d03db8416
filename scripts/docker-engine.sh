#!/usr/bin/env bash
# Make sure a Docker engine answers. Reuses a running one; otherwise starts dockerd (through
# systemd when it runs, else directly) and waits for `docker info`. Prints the pid of a dockerd
# it started directly (empty otherwise), so the caller can stop exactly that one.
set -euo pipefail
if docker info >/dev/null 2>&1; then exit 0; fi
if [ -d /run/systemd/system ] && systemctl start docker >/dev/null 2>&1; then
  :
else
  # its own session: the engine outlives the shell or job that started it (and its signals)
  setsid dockerd >/var/log/ccrp-dockerd.log 2>&1 < /dev/null &
  echo $!
fi
for _ in $(seq 1 60); do
  docker info >/dev/null 2>&1 && exit 0
  sleep 1
done
echo "ccrp: the Docker engine did not start (see /var/log/ccrp-dockerd.log)" >&2
exit 1
