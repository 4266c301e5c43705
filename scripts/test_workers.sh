#!/usr/bin/env bash
# How many pytest-xdist workers scripts/test.sh and scripts/test_blas_kernels.sh run the tests on: $TEST_WORKERS if
# set (0: all tests in the pytest process itself), else the CPUs this process may use, at most 4 (the suite's real-
# time process tests share the cores with the CPU-bound ones; more workers than cores slows both down).
set -euo pipefail
n=${TEST_WORKERS:-$(nproc)}
if ! [[ $n =~ ^[0-9]+$ ]]; then
  echo "TEST_WORKERS=$n: give a number of workers (0: none)" >&2
  exit 2
fi
[ -n "${TEST_WORKERS:-}" ] || n=$(( n > 4 ? 4 : n ))
echo "$n"
