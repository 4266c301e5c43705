#!/usr/bin/env bash
# How many pytest-xdist workers to run the tests on: $TEST_WORKERS if set (0: all tests in the pytest process),
# else the default given as $1: "0", or "cpus" for the CPUs this process may use, at most 4 (more workers than
# cores slows every test down). scripts/test.sh defaults to 0: under a CPU-busy machine its real-time pty/DDS tests
# are not reliable on workers yet (docs/architecture.md); scripts/test_blas_kernels.sh (numerical tests) to cpus.
set -euo pipefail
n=${TEST_WORKERS:-${1:-0}}
[ "$n" != cpus ] || n=$(( $(nproc) > 4 ? 4 : $(nproc) ))
if ! [[ $n =~ ^[0-9]+$ ]]; then
  echo "TEST_WORKERS=$n: give a number of workers (0: none)" >&2
  exit 2
fi
echo "$n"
