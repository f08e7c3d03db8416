#!/usr/bin/env bash
# Quick start on a fresh Debian/Ubuntu machine: install what is missing, then prepare the thesis
# lab fleet (inventories/lab.yaml): validate it, create its CA, issue every robot's certificates
# and render each clone's user-data and each robot's edge bundle under .ccrp/lab/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
ccrp=.venv/bin/ccrp
inv=inventories/lab.yaml
$ccrp fleet validate -i "$inv"
$ccrp vpn init -i "$inv"
for robot in nao1 nao2 turtlebot1; do
  $ccrp vpn issue-cert -i "$inv" --robot "$robot" >/dev/null
  $ccrp render cloud-init -i "$inv" --robot "$robot" > ".ccrp/lab/$robot.user-data"
  $ccrp render edge -i "$inv" --robot "$robot" --remote "cri-$robot" --out ".ccrp/lab/edge/$robot" 2>/dev/null
done
$ccrp vpn list -i "$inv"
