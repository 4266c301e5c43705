#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite: lint, then pytest. Usage: scripts/test.sh [pytest args]
# TEST_WORKERS=N runs the tests on N pytest-xdist workers (scripts/test_workers.sh); by default (0) all run in the
# pytest process: under a busy CPU a real-time pty test is not reliable on workers yet (docs/architecture.md).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/bootstrap.sh
.venv/bin/ruff check .
workers=$(scripts/test_workers.sh 0)
# Each test run gets its own DDS domain so parallel runs on one machine do not cross-talk; each worker uses the
# run's domain + its number (test/conftest.py), so the run takes domains base..base+workers-1, within 1..101.
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % (101 - (workers > 1 ? workers - 1 : 0))) + 1 ))}
# a test file's tests stay in one worker: its module fixtures (one board, one diagnosis) are built once; files go out
# in collection order, the long real-time files first (test/conftest.py LONG_FIRST), not by their number of tests
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile --no-loadscope-reorder "$@"
