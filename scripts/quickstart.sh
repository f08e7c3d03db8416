#!/usr/bin/env bash
# Quick start on a fresh Debian/Ubuntu machine (as root): install what is missing (Docker engine
# included), build the clone snapshot, bring up the thesis lab fleet (inventories/lab.yaml: nao1,
# nao2, turtlebot1) on Docker, start the three simulated robots and show the fleet's status.
# Re-running it converges; `ccrp fleet down -i inventories/lab.yaml` removes the fleet.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/docker-engine.sh >/dev/null
ccrp=.venv/bin/ccrp
inv=inventories/lab.yaml
$ccrp fleet validate -i "$inv" >/dev/null
$ccrp vpn init -i "$inv"
$ccrp snapshot build -i "$inv" --if-missing >/dev/null
$ccrp fleet up -i "$inv"
for robot in nao1 nao2 turtlebot1; do
  $ccrp robot sim -i "$inv" --robot "$robot"
done
echo "ccrp: waiting for the robots' nodes to register on their clones" >&2
for _ in $(seq 1 30); do
  [ "$($ccrp status -i "$inv" --json | grep -c '"vpn_connected": true')" = 3 ] && break
  sleep 1
done
$ccrp status -i "$inv"
