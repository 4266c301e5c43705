#!/usr/bin/env bash
# Set up (if needed), start the simulated board on a pseudo-terminal and the driver on it, and
# show the published acceleration and temperature live for a few seconds.
# Usage: scripts/demo.sh [seconds]   (default 8)
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/bootstrap.sh
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}
exec .venv/bin/python -m fbg_accel_sim.demo --seconds "${1:-8}"
