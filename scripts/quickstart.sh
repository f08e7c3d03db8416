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
  # --wait: until the robot's VPN is up and its node is registered on its clone's master
  $ccrp robot sim -i "$inv" --robot "$robot" --wait 60
done
$ccrp status -i "$inv"
