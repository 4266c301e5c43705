#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite: lint, then pytest. Usage: scripts/test.sh [pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/bootstrap.sh
.venv/bin/ruff check .
# Each test run gets its own DDS domain so parallel runs on one machine do not cross-talk.
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}
exec .venv/bin/python -m pytest "$@"
