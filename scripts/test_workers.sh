#!/usr/bin/env bash
# How many pytest-xdist workers to run the tests on: $TEST_WORKERS if set (0: all tests in the pytest process),
# else the default given as $1: a number, or "cpus" for the CPUs this process may use, at most $2 (default 4; more
# workers than cores slows every test down), and 0 on a single CPU (one worker would only add a process).
# scripts/test.sh asks for "cpus 2" (its real-time files run on one worker, so a third worker gains little and the
# suite was verified on two: docs/architecture.md); scripts/test_blas_kernels.sh (numerical tests) for "cpus".
set -euo pipefail
n=${TEST_WORKERS:-${1:-0}}
if [ "$n" = cpus ]; then
  max=${2:-4}
  n=$(( $(nproc) > max ? max : $(nproc) ))
  [ "$n" -gt 1 ] || n=0
fi
if ! [[ $n =~ ^[0-9]+$ ]]; then
  echo "TEST_WORKERS=$n: give a number of workers (0: none)" >&2
  exit 2
fi
echo "$n"
