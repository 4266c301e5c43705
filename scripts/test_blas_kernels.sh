#!/usr/bin/env bash
# Run the numerical tests (diagnosis, fit, dynamic calibration, calibration model) once under each OpenBLAS kernel
# family this CPU can run, forced with OPENBLAS_CORETYPE. The kernels round differently; a test that passes under one
# and fails under another asserts a result decided by rounding, which a user on another machine would not get.
# Usage: scripts/test_blas_kernels.sh [KERNEL ...]   (default: Prescott Haswell SkylakeX Zen; .ci/run calls it)
# The tests run on pytest-xdist workers, one per CPU (at most 4, none on a single CPU; TEST_WORKERS=N sets the number,
# 0 for none).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/bootstrap.sh
kernels=("$@")
[ ${#kernels[@]} -gt 0 ] || kernels=(Prescott Haswell SkylakeX Zen)
if [ "$(uname -m)" != x86_64 ]; then
  echo "test_blas_kernels: OpenBLAS core types are x86-64 kernels; this is $(uname -m): nothing to run"
  exit 0
fi
flags=$(grep -m1 '^flags' /proc/cpuinfo || true)
tests=$(ls test/test_diagnose*.py test/test_*fit*.py test/test_thermal_*.py test/test_dynamic_*.py test/test_adc_*.py \
  test/test_switch_profile.py test/test_search_lanes.py test/test_correction_terms.py test/test_chain_compensation.py \
  test/test_driver_chain_compensation.py test/test_low_reference.py test/test_reference_level.py \
  test/test_static_detector.py test/test_coefficient_uncertainty.py test/test_calibration_covariance_driver.py \
  test/test_field_check.py test/test_held_lowpass.py 2>/dev/null | grep -v '_process\.py$')
workers=$(scripts/test_workers.sh cpus)  # each worker on its own DDS domain: base..base+workers-1 (test/conftest.py)
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 101 ))}
corename='from fbg_accel_calibration.diagnosis.blas_threads import blas_core_names; import numpy as np
np.ones(2) @ np.ones(2); print(",".join(blas_core_names()))'
seen=" "
status=0
for k in "${kernels[@]}"; do
  case $k in
    SkylakeX|Cooperlake|SapphireRapids) need=avx512f ;;
    Haswell|Zen) need=avx2 ;;
    *) need=pni ;;  # SSE3, as /proc/cpuinfo names it
  esac
  if ! grep -qw "$need" <<<"$flags"; then
    echo "test_blas_kernels: $k skipped: this CPU has no $need"
    continue
  fi
  core=$(OPENBLAS_CORETYPE=$k .venv/bin/python -c "$corename")
  if [[ "$seen" == *" $core "* ]]; then
    echo "test_blas_kernels: $k skipped: it runs the $core kernels, already tested"
    continue
  fi
  seen="$seen$core "
  echo "test_blas_kernels: OPENBLAS_CORETYPE=$k ($core kernels)"
  # the workers inherit OPENBLAS_CORETYPE; test/conftest.py fails the run if one computes with another kernel
  # shellcheck disable=SC2086
  OPENBLAS_CORETYPE=$k .venv/bin/python -m pytest -p no:cacheprovider -n "$workers" --dist loadfile $tests || status=1
done
exit $status
