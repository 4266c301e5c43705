#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite: lint, then pytest. Usage: scripts/test.sh [pytest args]
# The tests run on two pytest-xdist workers (none on a single CPU: all tests in the pytest process); TEST_WORKERS=N
# sets the number, 0 for none (scripts/test_workers.sh). The real-time files (processes, ptys, DDS) run on one worker
# one after another as in a serial run, beside the other worker's files (test/conftest.py; docs/architecture.md).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/bootstrap.sh
.venv/bin/ruff check .
workers=$(scripts/test_workers.sh cpus 2)
# Each test run gets its own DDS domain so parallel runs on one machine do not cross-talk; each worker uses the
# run's domain + its number (test/conftest.py), so the run takes domains base..base+workers-1, within 1..101.
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % (101 - (workers > 1 ? workers - 1 : 0))) + 1 ))}
# a test file's tests stay in one worker, so its module fixtures (one board, one diagnosis) are built once, and all
# real-time files are one work unit (test/conftest.py pytest_xdist_make_scheduler); units go out in collection order,
# the real-time unit first (test/conftest.py run_real_time_first), not by their number of tests
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile --no-loadscope-reorder "$@"
