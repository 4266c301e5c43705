#!/usr/bin/env python3
"""Mutation testing of the pure core against its fast tests (mutmut 3, configured in pyproject.toml [tool.mutmut]).

Not a test and not in CI: every mutant is a pytest run of the tests that reach the mutated function (the five modules
hold ~3700 mutants: a killed one takes well under a second, a survivor runs all its tests, one that hangs runs into
mutmut's timeout; hours for all on the 2-core build machine). This script runs mutmut module by module (one mutmut
call each, one mutant at a time by default) on the mutants of the modules asked for that have no result yet, all of
them or a seeded random sample per module (``--sample N``); stopped, it resumes where it was. It reads mutmut's
results and writes a page: per module the mutants checked, killed and surviving (score = killed / checked; a mutant
no test reaches counts as surviving), and each survivor with its diff and, when it is one, the reason it is
equivalent (:data:`EQUIVALENT`: a mutant that cannot change what a user gets, so no test can kill it).

Each mutant's tests run fastest first and stop at the first failure, a failing hypothesis property is not shrunk,
and the slow tests of :data:`LEAVE_OUT` are not run (test/conftest.py, only under mutmut).

Modules and the tests that judge them (``pytest_add_cli_args_test_selection``; mutmut runs, for each mutant, the
tests of that selection that execute the mutated function):

* ``fbg_accel_driver.frame_codec``  -- test_frame_codec.py
* ``fbg_accel_driver.stream_decoder`` -- test_stream_decoder.py
* ``fbg_accel_driver.clock_sync`` -- test_clock_sync.py
* ``fbg_accel_driver.thermal_model`` (the calibration model and its loader) -- test_thermal_model.py,
  test_calibration_contract.py, test_thermal_model_edges.py
* ``fbg_accel_calibration.fit.thermal_fit`` (the eq. 28 fit) -- test_thermal_fit.py

Usage::

    nice -n 19 .venv/bin/python bench/mutation_check.py                   # every mutant; writes /tmp/mutation.md
    .venv/bin/python bench/mutation_check.py --modules frame_codec        # every mutant of one module
    .venv/bin/python bench/mutation_check.py --sample 40                  # 40 drawn per module
    .venv/bin/python bench/mutation_check.py --recheck-survivors          # the survivors again, after new tests
    .venv/bin/python bench/mutation_check.py --report-only --update-results  # the page from the results so far

The first run generates the mutants under ``mutants/`` (git-ignored) and collects which tests reach which function
(minutes); later runs reuse both for the files that did not change.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import random
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MUTMUT = [sys.executable, "-m", "mutmut"]
MODULES = {
    "frame_codec": "fbg_accel_driver/frame_codec.py",
    "stream_decoder": "fbg_accel_driver/stream_decoder.py",
    "clock_sync": "fbg_accel_driver/clock_sync.py",
    "thermal_model": "fbg_accel_driver/thermal_model.py",
    "thermal_fit": "fbg_accel_calibration/fit/thermal_fit.py",
}
# Slow tests left out of the mutation run (node-id prefix -> why the mutants they reach are judged without them); the
# conftest deselects them when mutmut runs a mutant. A survivor they alone would kill shows as a survivor here.
LEAVE_OUT: dict[str, str] = {
    "test/test_clock_sync.py::test_a_board_crystal_drifting_with_temperature_keeps_the_stamps": (
        "2 x 2.5 s of 180 000 observations each, reaching every ClockSync function: the same code and decisions (the "
        "drift line, the lower envelope, the stamps' error bound) are judged by the drift, burst, stall, reset and "
        "crystal-rate-change tests of the same file in a tenth of the time. Checked: of the clock's survivors of a "
        "run without it, it killed one alone (a window that kept its first bin), which "
        "test_a_change_of_the_crystal_rate_leaves_the_window_with_its_bins now kills"),
}
KILLED = {1, 3, 36, 37, -24, 24, 152, 255, -11, -9}  # test failure, pytest error, timeout, crash (mutmut/stats.py)
# Survivors that cannot change what a user gets, with the reason (mutant name -> reason); names are mutmut's, valid
# for the source as committed with this table.
EQUIVALENT: dict[str, str] = {
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcorrection_sum__mutmut_15": (
        "np.asarray(t_s, None) for np.asarray(t_s, float): every caller passes board times as a float array already"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁexpected_reference_counts__mutmut_1": (
        "the cache not read: the same value is worked out again, only slower"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ_coefficients_of__mutmut_10": (
        "equal_nan=None for True: temperatures with NaN then miss the cache and are worked out again, to the same "
        "values"),
    "fbg_accel_driver.thermal_model.x_normalise__mutmut_5": (
        "the reference without dtype=float: np.where with NaN makes it float either way"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁfrom_dict__mutmut_117": (
        "finite=None for finite=False: the flag is only tested for truth"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_15": (
        "<= for < on the board clock: a frame at the last frame's t_us never gets there (a duplicate or a stuck "
        "clock is handled before; with BOOT it is a reset either way)"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_4": (
        "or for and between 'a last seq' and 'a last board time': both are None until the first frame and set "
        "together with every frame after it"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_35": (
        "dt > 1 for dt > 0: the nominal interval differs only at 1 us, which no board gives (a read alone is an ADC "
        "conversion of ~40 us)"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_36": (
        ">= for > in the wrap test: at equality the step is half a wrap over, and round(0.5) adds 0 wraps"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_37": (
        "/ dt for * dt in the wrap test: the test only spares the rounding below it, where the wraps added round to "
        "0 (max(0, round(x)) is 0 for x <= 0.5, and the test is x > 0.5)"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_38": (
        "step - HALF_WRAP for step + HALF_WRAP in the wrap test: the same reason (below the true test the wraps "
        "added round to 0)"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ_accept__mutmut_46": (
        "max(1, ...) for max(0, ...) of the wraps added: the branch is taken only when the step is more than half a "
        "wrap over, where the rounded count is at least 1"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁfeed__mutmut_40": (
        ">= for > before counting the bytes ahead of a sync word: at equality it adds 0 bytes and moves pos to "
        "where it is"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ__init____mutmut_3": (
        "\"\" for None as the last seq: every use reads it together with the last board time, None until the "
        "first frame, and both are set together"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ__init____mutmut_5": (
        "None for 0 as the ADC_OVERRUN flag of the previous frame before there is one: the first frame sets it "
        "before any step reads it"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ__init____mutmut_6": (
        "1 for 0 as the ADC_OVERRUN flag of the previous frame before there is one: the same reason"),
    "fbg_accel_driver.stream_decoder.xǁStreamDecoderǁ__init____mutmut_4": (
        "\"\" for None as the last board time: it is read only once a last seq exists, and both are set together"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstatus__mutmut_9": (
        "the rate scaled by 1e6 + 1 for 1e6: the figure moves by a millionth of itself (2e-5 ppm at 20 ppm, 5e-4 at "
        "the 500 ppm clamp), below the 0.01 ppm it is rounded to; it can change the last digit only when within "
        "that of a rounding boundary"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_7": (
        "and for or between 'no applied offset' and 'no board time it refers to': both are None after a (re)start "
        "and set together at every stamp"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_24": (
        ">= for > at the step threshold of the mapping's error: the error is a float difference of the fitted line and the "
        "observations (ppm slopes, means), equal to 50 ms only on inputs of measure zero; no recording reads differently"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_33": (
        "<= for < at the end of the warm-up: only a frame whose board time (t_us x 1e-6, a float) lies exactly "
        "warmup_s after the start's differs; that one frame may then slew by the warm-up's limit, at most "
        "(5e-3 - 5e-4) x 10 ms = 45 us more at 100 Hz, inside the stamps' stated error"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_63": (
        "the step threshold scaled by 1e9 + 1 for 1e9: 50 000 000.05 ns instead of 50 000 000 ns, compared with an "
        "integer number of ns: the same decision for every integer"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_71": (
        "the read-jitter band scaled by 1e9 + 1 for 1e9: 2 000 000.002 ns instead of 2 000 000 ns; compared with and "
        "subtracted from integer ns and rounded, it gives the same decision and the same integer"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_75": (
        ">= for > at the band: at exactly the band the offset moves by round(beyond - band) = 0"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_96": (
        "the in-band slew limit scaled by 1e9 + 1 for 1e9: 5 000.000005 ns instead of 5 000 ns per sample at 100 Hz, "
        "which the rounding to integer ns takes away"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_117": (
        "(base or 1) for (base or 0): the integer base is set at the first observation, before any stamp, and is 0 "
        "only if the steady clock read exactly 1000 x the board's t_us then; the stamp would then move by 1 ns"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_120": (
        "the applied offset scaled by 1e9 + 1 for 1e9 ns/s: it is the offset left after the integer base (board drift "
        "x elapsed time, tens of ms over hours), so the stamp moves by under 1 ns"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁstamp__mutmut_123": (
        "< for <= in the never-back guard: it differs only for a stamp equal to the previous one to the ns, which "
        "needs two frames at the same board time (the decoder drops them before stamping: a duplicate or a stuck "
        "clock) or a 1-in-10^7 coincidence as a hold ends; any stamp below the previous one is held either way"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_4": (
        "zip(strict=None) for strict=True: the two lists are made from the same bins, one entry each"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_7": ("zip without strict=True: the same reason"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_8": ("zip(strict=False): the same reason"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_48": (
        ">= for > between consecutive hull x: they are the board times of different bins (one bin per time slot), "
        "strictly increasing, so never equal"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_52": (
        "1.0 for 0.0 after the loop: never reached, the hull keeps the first and the last point (x strictly "
        "increasing, at least 3 bins), and the last pair ends at the largest x, at or right of the mean"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ__init____mutmut_5": (
        "None for 0 as the latest host-minus-steady offset: every observation sets it, and only stamp, which follows "
        "an observation, reads it"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ__init____mutmut_6": (
        '1 for 0 as the latest host-minus-steady offset: the same reason'),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ__init____mutmut_8": (
        "None for 0 as the agreed host-minus-steady offset: the first observation is a new read and sets it before "
        "stamp reads it"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ__init____mutmut_9": (
        '1 for 0 as the agreed host-minus-steady offset: the same reason'),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_3": (
        "None for 0.0 as the line's offset after a (re)start: the first observation after it makes a bin and refits, "
        "setting it before anything reads it"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_4": (
        "1.0 for 0.0 as the line's offset after a (re)start: the same reason"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_7": (
        "\"\" for None as the applied offset: it is tested together with the board time it refers to (None until the "
        "first stamp), and both are set together"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_9": (
        "\"\" for None as the board time of the first observation: it is read with the last observation's time, None "
        "until that first observation sets both"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_10": (
        '"" for None as the last observation\'s board time: the same reason (primed reads the two together)'),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_11": (
        "None for 0 as the steady time of the first observation: set with that observation, read only after it (as "
        "_clear__mutmut_12)"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_13": (
        "None for 0 as the steady time of the last observation: every observation sets it, and primed reads it only "
        "once there was one"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_14": ("1 for 0 there: the same reason"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_35": (
        "steady + 1000 t_us for steady - 1000 t_us as the integer base: like observe__mutmut_37, any integer base "
        "cancels (every offset is taken relative to it, every stamp adds it back); the offsets then sit near -2 t0 "
        "(hours at most), still far below a ns of float spacing"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_48": (
        "<= for < at the restart threshold (an observation 50 ms below the line): the distance is a float difference of "
        "the fitted line and an observation, equal to the threshold only on inputs of measure zero"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_58": (
        "/ for // in the bin index: the board time since the reference is never negative (a board time going back is "
        "a reset, which clears the reference), and int() of a positive quotient is its floor"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_59": (
        "board_s + ref for board_s - ref in the bin index: the 0.5 s bins keep their width and order, only where "
        "their edges fall moves (aligned to -ref instead of ref), an arbitrary phase; the minima per bin and the line"
        " through them stay as good (every stamp and drift bound of the tests holds)"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_65": (
        "<= for < when a frame ties the open bin's minimum offset to the ns: either frame is a lowest point of the "
        "bin, a coincidence of two delays equal to the ns"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_94": (
        ">= for > when the window is full: the drift line is fitted over 399 bins of 0.5 s instead of 400 (199.5 s "
        "instead of 200 s), a window 0.25 % shorter, within the estimator's own scatter"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_refit__mutmut_14": (
        "board_s + ref for board_s - ref as the hull's x: every x moves by the same 2 ref, and a slope does not "
        "depend on where x starts"),
    "fbg_accel_driver.thermal_model.x__agrees__mutmut_3": (
        "the number parser's label None for \"\": the label only goes into the message of the error it raises, and that"
        " error is caught here"),
    "fbg_accel_driver.thermal_model.x__agrees__mutmut_4": (
        "None for ValueError as the error the number parser raises: raising None is a TypeError, caught here like the"
        " ValueError"),
    "fbg_accel_driver.thermal_model.x__agrees__mutmut_8": (
        "the label \"XXXX\" for \"\": the same reason as __agrees__mutmut_3"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcorrection_sum__mutmut_17": (
        "np.asarray(t_s) without float: every caller passes board times as a float array already (as "
        "correction_sum__mutmut_15)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcorrection_sum__mutmut_20": (
        "zip(strict=None) for strict=True: the state holds one entry per correction term by construction (new_state)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcorrection_sum__mutmut_23": (
        "zip without strict=True: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcorrection_sum__mutmut_24": (
        "zip(strict=False): the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_3": (
        "the header comment in lower case: a YAML comment, which no reader of the file interprets"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_4": (
        "the header comment in upper case: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_8": (
        "sort_keys=None for False: PyYAML only tests it for truth"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_9": (
        "width=None for 100: only where the dumper wraps long flow lists moves; every value reads back the same"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_13": (
        "no width (PyYAML's 80) for 100: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_15": (
        "width=101 for 100: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_22": (
        "encoding \"UTF-8\" for \"utf-8\": Python reads codec names without regard to case"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_17": (
        "encoding=None (the locale's) for utf-8: safe_dump escapes every character outside ASCII (allow_unicode is "
        "off) and the header is ASCII, so the text is the same bytes in any encoding "
        "(test_a_saved_file_is_utf8_whatever_the_locale_... writes a degree sign under LC_ALL=C)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁsave__mutmut_19": (
        "no encoding for utf-8: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ__eq____mutmut_12": (
        "array_equal without equal_nan=True: no array field can hold NaN (the constructor refuses NaN in M, b, the "
        "noise terms and the reference levels), so NaN never meets NaN"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ__eq____mutmut_15": (
        "array_equal without equal_nan=True: no array field can hold NaN (the constructor refuses NaN in M, b, the "
        "noise terms and the reference levels), so NaN never meets NaN"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ__eq____mutmut_24": (
        "array_equal without equal_nan=True: no array field can hold NaN (the constructor refuses NaN in M, b, the "
        "noise terms and the reference levels), so NaN never meets NaN"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcoefficients_at__mutmut_1": (
        "the cache not read: the same coefficients are worked out again, only slower"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcoefficients_at__mutmut_2": (
        "the cache read under None: a miss, the same coefficients worked out again"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcoefficients_at__mutmut_4": (
        "the cache emptied above 256 entries instead of at 256: one entry more of memory, the same values"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcoefficients_at__mutmut_5": (
        "the cache emptied at 257 entries: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁexpected_reference_counts__mutmut_2": (
        "the cache read under None: a miss, the same level worked out again"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁexpected_reference_counts__mutmut_17": (
        "the cache emptied above 256 entries instead of at 256: one entry more of memory, the same values"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁexpected_reference_counts__mutmut_18": (
        "the cache emptied at 257 entries: the same reason"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁexpected_reference_counts__mutmut_19": (
        "None cached for the level: the next call reads None as a miss and works the same level out again"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_3": (
        "4096 for 4095 counts in the span of Psi: scales a real-valued span by 1.0002 against its bound; only a "
        "calibration whose sensitivity lies within 0.02 % of the bound reads differently, and the bound is a "
        "plausibility limit orders of magnitude from any real sensor's (docs/calibration_file.md)"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_13": (
        "zip(strict=None) for strict=True: one M(T) per temperature by construction"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_16": (
        "zip without strict=True: the same reason"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_17": (
        "zip(strict=False): the same reason"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_29": (
        "> for >= at the 5 g span bound: a real-valued span exactly at the bound has no weight (the same rule)"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_31": (
        "/ sign for * sign: the sign of the largest entry of a unit vector is +1 or -1, never 0, and dividing by +-1 "
        "is multiplying by it"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_51": (
        ">= for > at 0.99 (the direction named by its axis): a real-valued component exactly at 0.99 has no weight "
        "(the same rule)"),
    "fbg_accel_driver.thermal_model.x_check_plausible__mutmut_104": (
        ">= for > at the output bound: a real-valued output exactly at the bound has no weight (the same rule)"),
    # the calibration model and its loader: survivors of test_thermal_model_edges.py and the tests before it
    "fbg_accel_driver.thermal_model.x__evaluate_grid__mutmut_3": (
        "each grid point held for 50 samples also without correction terms: eq. 24 and eq. 28 alone are stateless, "
        "so every sample of a point gives the same output and the judged one is unchanged (only slower)"),
    "fbg_accel_driver.thermal_model.x__evaluate_grid__mutmut_5": (
        "each grid point held for 2 samples without correction terms: eq. 24 and eq. 28 alone are stateless, so the "
        "judged output is unchanged"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_5": (
        "errstate(all=None) around the sensitivity check: it runs only after check_plausible evaluated the same M(T) "
        "at the same temperatures to finite outputs (an overflow there gives inf or NaN and an earlier refusal), and "
        "numpy ignores underflow by default, so no floating-point warning can arise in it"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_68": (
        "max_line_width=None (numpy's 75) for 1000 when printing M(T): a row of three entries printed to 4 decimals "
        "is at most ~42 characters (-1.2346e+300), so no row wraps either way"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_71": (
        "max_line_width left out (75) when printing M(T): a row printed to 4 decimals is at most ~42 characters, no "
        "row wraps either way"),
    "fbg_accel_driver.thermal_model.x__insensitive__mutmut_73": (
        "max_line_width 1001 for 1000 when printing M(T): a row printed to 4 decimals is at most ~42 characters"),
    "fbg_accel_driver.thermal_model.x__section__mutmut_30": (
        "finite=None for finite=False: the flag is only tested for truth"),
    "fbg_accel_driver.thermal_model.x__text__mutmut_3": (
        "d.get(key, None) for d.get(key, \"\"): an absent key then gives None, which the next line turns into \"\" as "
        "it does an empty key"),
    "fbg_accel_driver.thermal_model.x__text__mutmut_5": (
        "d.get(key) for d.get(key, \"\"): an absent key gives None, which the next line turns into \"\""),
    "fbg_accel_driver.thermal_model.x_check_plausible__mutmut_47": (
        "reshape(-2, 3) for reshape(-1, 3): numpy (2.x) takes any negative size as the one to infer, the same array"),
    "fbg_accel_driver.thermal_model.x_migrate__mutmut_15": (
        "exact=None for exact=False: the flag is only tested for truth"),
    "fbg_accel_driver.thermal_model.x_normalise__mutmut_3": (
        "the reference without dtype=float: the division by it is in float64 either way (the axis counts are made "
        "float64), of the same values"),
    "fbg_accel_driver.thermal_model.x_normalise__mutmut_16": (
        "the axis counts without dtype=float: divided by the float64 reference, in float64, the same values"),
    "fbg_accel_driver.thermal_model.x_normalise__mutmut_18": (
        "the axis counts without dtype=float: divided by the float64 reference, in float64, the same values"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ_coefficients_of__mutmut_13": (
        "equal_nan left out (False): temperatures with NaN miss the cache and are worked out again, to the same "
        "values"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ_coefficients_of__mutmut_15": (
        "equal_nan=False: temperatures with NaN miss the cache and are worked out again, to the same values"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ_coefficients_of__mutmut_18": (
        "None for () while the batch's coefficients are worked out: nothing reads it before it is set two lines "
        "below (coefficients() does not), and apply_counts sets None when it returns either way"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁ_coefficients_of__mutmut_25": (
        "np.array(temp_c) for np.array(temp_c, copy=True): copying is np.array's default"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁapply_counts__mutmut_9": (
        "the axis counts not made float here: every use makes them float64 before any arithmetic (map_counts, "
        "normalise, the terms with np.asarray(..., float) or beside the float64 reference)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁapply_counts__mutmut_11": (
        "the axis counts without dtype=float: every use makes them float64 before any arithmetic (map_counts, "
        "normalise, the terms with np.asarray(..., float) or beside the float64 reference)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁapply_counts__mutmut_20": (
        "the temperatures not made float here: base_acceleration and every term that reads them (thermal_lag, "
        "thermal_hysteresis) make them float64 before any arithmetic"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁapply_counts__mutmut_22": (
        "the temperatures without dtype=float: base_acceleration and the terms that read them make them float64 "
        "before any arithmetic"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁbase_acceleration__mutmut_4": (
        "Psi not made float here: einsum casts it to float64 beside M(T) before multiplying, the same products"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁbase_acceleration__mutmut_6": (
        "Psi without dtype=float: einsum casts it to float64 beside M(T) before multiplying, the same products"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁbase_acceleration__mutmut_14": (
        "the temperatures not made float here: scaled_temperature makes them float64 before any arithmetic"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁbase_acceleration__mutmut_16": (
        "the temperatures without dtype=float: scaled_temperature makes them float64 before any arithmetic"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁbase_acceleration__mutmut_26": (
        "einsum subscripts in capitals: the same contraction (subscripts are letters of either case)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁcoefficients__mutmut_16": (
        "einsum subscripts in capitals: the same contraction (subscripts are letters of either case)"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁfrom_dict__mutmut_8": (
        "finite=None for finite=False: the flag is only tested for truth"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁfrom_dict__mutmut_93": (
        "finite=None for finite=False: the flag is only tested for truth"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁfrom_dict__mutmut_105": (
        "finite=None for finite=False: the flag is only tested for truth"),
    "fbg_accel_driver.thermal_model.xǁThermalCalibrationǁload__mutmut_35": (
        "encoding 'UTF-8' for 'utf-8': Python's codec names are case-insensitive"),
    "fbg_accel_driver.clock_sync.x_lower_envelope_slope__mutmut_39": (
        "< for <= when a hull point is collinear with its neighbours: keeping it splits one edge into two of the "
        "same slope, so the slope at the mean board time is the same"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_37": (
        "another integer base for the offsets (steady - 1001 t_us for steady - 1000 t_us at the first frame): every "
        "offset is taken relative to it and every stamp adds it back, so it cancels"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁobserve__mutmut_84": (
        "<= for < between bin indices: an equal index took the branch before"),
    "fbg_accel_driver.clock_sync.xǁClockSyncǁ_clear__mutmut_12": (
        "1 for 0 as the steady time of the first observation before there is one: it is set with that observation, "
        "and read only after it"),
    # --- fbg_accel_calibration.fit.thermal_fit (the eq. 28 fit) ---
    **{f"fbg_accel_calibration.fit.thermal_fit.{name}": reason for name, reason in {
        # conversions that change nothing: what they convert is already of that type, or converted where it is used
        "x_check_pose_excitation__mutmut_3": (
            "the cells' sample counts without dtype=float: they are floats already (CellAccumulator.finish), and every "
            "use sums them or divides by them"),
        "x_check_pose_excitation__mutmut_5": ("the counts without dtype: the same reason"),
        "x_check_level_consistency__mutmut_11": ("a level's sample counts with dtype=None: the same reason"),
        "x_check_level_consistency__mutmut_13": ("a level's sample counts without dtype: the same reason"),
        "x_level_excitation__mutmut_12": ("a level's sample counts with dtype=None: the same reason"),
        "x_level_excitation__mutmut_14": ("a level's sample counts without dtype: the same reason"),
        "x_count_orientations__mutmut_3": ("the sample counts with dtype=None: the same reason"),
        "x_count_orientations__mutmut_5": ("the sample counts without dtype: the same reason"),
        "x_reference_range__mutmut_3": ("the sample counts with dtype=None: the same reason"),
        "x_reference_range__mutmut_5": ("the sample counts without dtype: the same reason"),
        "x_design_matrix__mutmut_3": (
            "Psi with dtype=None: it is written into the float matrix X, which converts it; callers pass floats"),
        "x_design_matrix__mutmut_5": ("Psi without dtype: the same reason"),
        "x_design_matrix__mutmut_8": (
            "tau with dtype=None: it is multiplied into the float matrix X (np.multiply out=X), which converts it"),
        "x_design_matrix__mutmut_10": ("tau without dtype: the same reason"),
        "x_reference_reach_warnings__mutmut_8": (
            "the reference range with dtype=None: its bounds are only compared and printed with .2f, the same for "
            "integers; the YAML and reference_range give floats"),
        "x_reference_reach_warnings__mutmut_10": ("the reference range without dtype: the same reason"),
        "x_temperature_levels__mutmut_3": (
            "the temperatures with dtype=None: np.isfinite, TemperatureClusters (np.asarray float) and the bincount "
            "weights read integers as the same values; callers pass floats"),
        "x_temperature_levels__mutmut_5": ("the temperatures without dtype: the same reason"),
        "x_temperature_levels__mutmut_9": ("the labels' dtype=None: np.full of -1 is int64 by default"),
        "x_temperature_levels__mutmut_12": ("the labels without dtype: the same reason"),
        "xǁTemperatureClustersǁadd__mutmut_4": (
            "the temperatures with dtype=None: sorted and compared the same, and stored next to the float clusters "
            "(np.r_ makes them float)"),
        "xǁTemperatureClustersǁadd__mutmut_6": ("the temperatures without dtype: the same reason"),
        "xǁTemperatureClustersǁfinish__mutmut_3": ("the bin counts with dtype=None: a list of Python ints is int64"),
        "xǁTemperatureClustersǁfinish__mutmut_5": ("the bin counts without dtype: the same reason"),
        "xǁTemperatureClustersǁlabels__mutmut_3": (
            "the temperatures with dtype=None: searchsorted and the bin arithmetic give the same for integers"),
        "xǁTemperatureClustersǁlabels__mutmut_5": ("the temperatures without dtype: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_14": (
            "the references with dtype=None: every caller passes floats (Recording, fit_stream's float buffers), and "
            "the sums of integers would be the same floats"),
        "xǁCellAccumulatorǁadd__mutmut_16": ("the references without dtype: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_19": (
            "the pose ids with dtype=None: every caller passes int64 (Recording.pose_id is dtype int, fit_stream's "
            "buffers are int64)"),
        "xǁCellAccumulatorǁadd__mutmut_21": ("the pose ids without dtype: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_24": (
            "the level labels with dtype=None: every caller passes int64 (temperature_levels, fit_stream's buffers, "
            "check_recording_excitation)"),
        "xǁCellAccumulatorǁadd__mutmut_26": ("the level labels without dtype: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_45": ("the run ids with dtype=None: fit_stream, the one caller that gives runs, "
                                             "passes int64"),
        "xǁCellAccumulatorǁadd__mutmut_47": ("the run ids without dtype: the same reason"),
        "xǁCellAccumulatorǁfinish__mutmut_27": ("the sums with dtype=None: lists of float arrays are float"),
        "xǁCellAccumulatorǁfinish__mutmut_29": ("the sums without dtype: the same reason"),
        "xǁCellAccumulatorǁfinish__mutmut_78": (
            "the visit lengths with dtype=None: a list of ints is int64; only an empty one (no sample added) becomes "
            "float, and the fit refuses 'no usable static samples' before it reads them"),
        "xǁCellAccumulatorǁfinish__mutmut_80": ("the visit lengths without dtype: the same reason"),
        "xǁCellAccumulatorǁfinish__mutmut_11": ("reshape(-2, 3) for reshape(-1, 3): numpy infers any negative size"),
        "xǁCellAccumulatorǁfinish__mutmut_31": ("reshape(-2, ...) of the sums: the same reason"),
        "x_scaled_condition__mutmut_30": ('float("INF") for float("inf"): Python reads it without regard to case'),
        "x_check_recording_excitation__mutmut_55": (
            "the level labels as float zeros: CellAccumulator.add converts them to int64"),
        "x_check_recording_excitation__mutmut_57": ("the same, without dtype"),
        "x_check_recording_excitation__mutmut_59": (
            "degree 1 for 0 with tau = 0: the added columns Psi tau and tau are zero, and the check reads only the "
            "reference sums, the counts and the Psi columns, which are the same"),
        # zip(strict=...): the sequences have one entry each by construction
        "xǁTemperatureClustersǁadd__mutmut_32": ("zip(strict=None) for strict=True: lo and hi have one entry per "
                                                 "cluster by construction"),
        "xǁTemperatureClustersǁadd__mutmut_35": ("zip without strict=True: the same reason"),
        "xǁTemperatureClustersǁadd__mutmut_38": ("zip(strict=False): the same reason"),
        "xǁTemperatureClustersǁfinish__mutmut_19": ("zip(strict=None) for strict=True: the same reason"),
        "xǁTemperatureClustersǁfinish__mutmut_22": ("zip without strict=True: the same reason"),
        "xǁTemperatureClustersǁfinish__mutmut_23": ("zip(strict=False): the same reason"),
        "xǁCellAccumulatorǁ_add_visit_sums__mutmut_12": (
            "zip(strict=None) for strict=True: the starts and ends of the visits have one entry each by construction"),
        "xǁCellAccumulatorǁ_add_visit_sums__mutmut_15": ("zip without strict=True: the same reason"),
        "xǁCellAccumulatorǁ_add_visit_sums__mutmut_16": ("zip(strict=False): the same reason"),
        # the same values by another way (memory, speed, the order of additions only)
        "xǁCellAccumulatorǁ__init____mutmut_4": ("no buffer: design_matrix makes a new matrix per chunk, the same values"),
        "xǁCellAccumulatorǁadd__mutmut_7": ("the buffer not passed (out=None): the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_11": ("the buffer not passed: the same reason"),
        "x_accumulate_cells__mutmut_14": (
            "a chunk of 2 rows for 1 when there are no rows: nothing is accumulated either way"),
        "xǁCellAccumulatorǁadd__mutmut_69": (
            "<= for < in the choice between contiguous slices and a stable sort to group the rows by cell: both give "
            "each cell the same rows, so the same sums (up to the order of the additions)"),
        "xǁCellAccumulatorǁadd__mutmut_70": ("/ 64 for // 64 in that choice: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_71": ("// 65 for // 64 in that choice: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_86": (
            "a piece's X^T X and X^T G worked out again instead of taken from the visit sums: the same values"),
        "xǁCellAccumulatorǁadd__mutmut_118": ("the same (worked out again)"),
        "xǁCellAccumulatorǁ_add_visit_sums__mutmut_18": (
            "None for a piece's sums: add() then works them out again from the same rows"),
        "xǁCellAccumulatorǁadd__mutmut_93": (
            "argsort kind None for 'stable' when grouping interleaved rows: only the order of a cell's rows within "
            "its sums changes (the order of the additions)"),
        "xǁCellAccumulatorǁadd__mutmut_95": ("argsort without kind: the same reason"),
        "xǁCellAccumulatorǁadd__mutmut_97": ("argsort kind 'STABLE': numpy reads the kind without regard to case"),
        "xǁTemperatureClustersǁadd__mutmut_22": (
            "argsort kind None for 'stable' over the clusters' lowest temperatures: clusters with equal lowest "
            "temperatures are merged (taking the larger highest), whatever their order"),
        "xǁTemperatureClustersǁadd__mutmut_24": ("argsort without kind: the same reason"),
        "xǁTemperatureClustersǁadd__mutmut_26": ("argsort kind 'STABLE': numpy reads the kind without regard to case"),
        "xǁCellAccumulatorǁadd__mutmut_140": ('einsum "NI,NI->I" for "ni,ni->i": the same contraction'),
        "xǁCellStatsǁcell_rss__mutmut_18": ('einsum subscripts in upper case: the same contraction'),
        "xǁCellStatsǁcell_rss__mutmut_27": ('einsum subscripts in upper case: the same contraction'),
        "xǁCellStatsǁvisit_scatter__mutmut_31": ('einsum subscripts in upper case: the same contraction'),
        "xǁCellAccumulatorǁ_add_visits__mutmut_9": ("reduceat without axis=0: 0 is its default"),
        "xǁCellAccumulatorǁ_add_visits__mutmut_36": (
            "len(starts) >= 1 for > 1: with one start there is no closed visit, and the branch adds a zero matrix and "
            "no length"),
        # state that is set before it is read
        "xǁCellAccumulatorǁ__init____mutmut_29": (
            "None for zeros as the open visit's sum before there is one: read only while a visit is open (the first "
            "chunk opens one and sets it with the visit)"),
        "xǁCellAccumulatorǁ__init____mutmut_31": ("None for 0 as the open visit's length: the same reason"),
        "xǁCellAccumulatorǁ__init____mutmut_32": ("1 for 0 as the open visit's length: the same reason"),
        "xǁCellAccumulatorǁ_close_visit__mutmut_10": (
            "\"\" for None as the open visit once closed: _add_visits sets the next open visit right after, and finish "
            "is the accumulator's last call"),
        "xǁCellAccumulatorǁadd__mutmut_40": (
            "run label 1 for 0 when no runs are given: the label only groups the cells, and without runs every row of "
            "every chunk gets the same one (accumulate_cells, the one caller without runs)"),
        "x_sensor_id_of__mutmut_10": (
            "\"\" for None as the first recorded id: '' or sid is sid (or None) as None or sid is, from the first part"),
        "x_sensor_id_of__mutmut_21": (
            "part.get('source') even for a part that is no dict: reached only for a part that names a sensor, which "
            "only a dict does (_recorded_sensor_id)"),
        "x_check_pose_excitation__mutmut_6": (
            "and for or between 'no cells' and 'no samples': a cell exists only for the rows that fall in it, so the "
            "samples are none exactly when the cells are none"),
        "x_check_pose_excitation__mutmut_9": ("count.sum() < 0 for <= 0: the same reason (a sum of 0 means no cells)"),
        "xǁCellAccumulatorǁadd__mutmut_104": (
            "each sorted key compared with the first instead of its predecessor: every row after the first cell then "
            "becomes its own piece, added to the cell its own key names: the same sums, in more additions"),
        "x_count_orientations__mutmut_7": (
            "gsum * count for gsum / count: a cell's direction is the same (count^2 > 0 times its mean)"),
        "x_count_orientations__mutmut_8": (
            "count >= 0 for > 0: a cell exists only for the rows that fall in it, so every count is >= 1"),
        "x_count_orientations__mutmut_10": ("the same, in the other mask of that line"),
        "x_reference_range__mutmut_8": ("count >= 0 for > 0: the same reason"),
        "x_reference_range__mutmut_10": ("the same, in the other mask of that line"),
        "xǁTemperatureClustersǁlabels__mutmut_19": (
            "bins >= 1 for > 1: a cluster of one bin then adds min(..., bins - 1) = 0 to its labels"),
        "x__direction_text__mutmut_2": (
            "/ sign for * sign: the sign of the largest component of a unit vector is +1 or -1, never 0"),
        "x_check_level_consistency__mutmut_102": (
            "the bound printed as 101 x 0.3 = 30.3 % with .0f: '30' either way"),
        # strict for non-strict where the compared quantity is computed in floating point from measured values (a
        # cosine, a spread, a ratio, a condition number, |g| against g/2): it equals the bound only on a set of inputs
        # of measure zero, so no recording a user can give reads differently
        "x__direction_text__mutmut_14": ("<= for < at 5e-3 (a component of a unit vector printed as 0.00)"),
        "x_check_level_consistency__mutmut_15": ("<= for < at the level's pose-spread bound"),
        "x_check_level_consistency__mutmut_74": ("< for <= at the 30 % bound of a ratio of fitted spreads"),
        "x_check_pose_excitation__mutmut_21": ("> for >= at the pose-spread bound"),
        "x_check_pose_excitation__mutmut_37": ("<= for < in naming the shape (coincide), a singular value's ratio"),
        "x_check_pose_excitation__mutmut_43": ("<= for < in naming the shape (collinear), a singular value's ratio"),
        "x_check_pose_excitation__mutmut_69": (">= for > at the 1e-9 Psi spread of identical samples"),
        "x_count_orientations__mutmut_31": (">= for > at the cosine of the orientation tolerance"),
        "x_level_excitation__mutmut_16": ("> for >= at the pose-spread bound"),
        "x_reference_reach_warnings__mutmut_16": (">= for > at half of g down (a component of a unit-vector angle "
                                                  "reading times g)"),
        "x_reference_reach_warnings__mutmut_20": ("<= for < at half of g up (the same)"),
        "x_solve_normal_equations__mutmut_5": ("<= for < at 1 / rcond of a computed condition number"),
        "xǁTemperatureClustersǁadd__mutmut_12": (
            ">= for > in the first split of a block: neighbours exactly one gap apart, split there, are merged again by "
            "the loop that merges the clusters of the parts with the rule <= gap (the part-merge, mutant 42, is "
            "killed by the test of readings one gap apart)"),
        "x_temperature_scaling__mutmut_15": (
            ">= for > at a half-range of exactly 0.5 degC (20.0 and 21.0 degC): the scale is then 0.5 instead of 1, "
            "which rescales the polynomial's variable and its coefficients together: the same model, the same "
            "outputs up to rounding"),
    }.items()},
}


def meta_results(path: str) -> dict[str, int | None]:
    """mutmut's exit code per mutant of one source file (None: not checked yet)."""
    meta = ROOT / "mutants" / (path + ".meta")
    if not meta.is_file():
        return {}
    return json.loads(meta.read_text())["exit_code_by_key"]


def forget(path: str, names: set[str]) -> None:
    """Mark the mutants ``names`` of one source file as not checked: mutmut keeps a result until the function's source
    changes, so a survivor is judged again by new tests only once forgotten."""
    meta = ROOT / "mutants" / (path + ".meta")
    data = json.loads(meta.read_text())
    for name in names & data["exit_code_by_key"].keys():
        data["exit_code_by_key"][name] = None
    meta.write_text(json.dumps(data))


def mutants_out_of_date(modules: list[str]) -> bool:
    """Whether a module has no mutants yet or its source changed since they were made: mutmut then regenerates them
    (keeping the results of the functions whose source did not change), which a run of named mutants alone does
    not do."""
    for m in modules:
        made = ROOT / "mutants" / (MODULES[m] + ".meta")
        if not made.is_file() or (ROOT / MODULES[m]).stat().st_mtime > made.stat().st_mtime:
            return True
    return False


def run_mutmut(names: list[str], max_children: int) -> None:
    """``mutmut run`` on ``names`` (all mutants of the configured modules when empty), in one call (one clean run
    of the tests they need, then one fork per mutant; mutmut records each result as it comes, so an interrupted
    run loses at most the mutants in flight)."""
    generate_only = names == ["__generate_only__"]  # no mutant has that name: mutmut generates, maps, then says so
    subprocess.run([*MUTMUT, "run", "--max-children", str(max_children), *names], cwd=ROOT, check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL if generate_only else None,
                   env={**os.environ, "MUTATION_LEAVE_OUT": ";".join(LEAVE_OUT)})


def diff_of(name: str, path: str) -> str:
    """The mutated lines of mutant ``name`` of source file ``path`` (what ``mutmut show`` prints, in this process)."""
    from mutmut.mutation.diff_apply import get_diff_for_mutant

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        out = get_diff_for_mutant(name, path=path)
    finally:
        os.chdir(cwd)
    return "\n".join(ln for ln in out.splitlines() if ln[:1] in "+-" and not ln.startswith(("+++", "---")))


def page(rows: list[dict], survivors: list[tuple[str, str]], command: str) -> str:
    lines = ["# Mutation testing of the pure core", "", f"Regenerate: `{command}`", "",
             "Run with mutmut 3.8.1 (pyproject.toml `[tool.mutmut]`) on the 2-core build machine, against the fast tests "
             "named in bench/mutation_check.py (left out of the run there: "
             + ", ".join(f"`{t.split('::')[-1]}`" for t in LEAVE_OUT) + "). Score = killed / checked; a mutant no "
             "test reaches counts as surviving; a mutant that hangs is killed by mutmut's timeout.", "",
             "| module | mutants | checked | killed | survived | of them equivalent | score | score without the "
             "equivalent |", "|---|---|---|---|---|---|---|---|"]
    for r in [*rows, {"module": "**all**", **{k: sum(r[k] for r in rows) for k in ("total", "checked", "killed",
                                                                                    "survived", "equivalent")}}]:
        c, k, e = r["checked"], r["killed"], r["equivalent"]
        score = f"{100 * k / c:.1f} %" if c else "-"
        clean = f"{100 * k / (c - e):.1f} %" if c > e else "-"
        lines.append(f"| {r['module']} | {r['total']} | {c} | {k} | {r['survived']} | {e} | {score} | {clean} |")
    total = sum(r["total"] for r in rows)
    checked = sum(r["checked"] for r in rows)
    if checked < total:
        lines += ["", f"{checked} of the {total} mutants ({100 * checked / total:.0f} %) have a result: a module's "
                  "figures are over all its mutants only where checked = mutants; the others have not been run (yet)."]
    lines += ["", "## Survivors", "", "Equivalent ones carry the reason no test can kill them; the others are gaps of "
              "the tests still open.", ""]
    for name, diff in survivors:
        reason = EQUIVALENT.get(name)
        lines += [f"- `{name}`: " + (f"equivalent: {reason}" if reason else "**not killed yet**"), "", "  ```diff",
                  *[f"  {ln}" for ln in diff.splitlines()], "  ```", ""]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modules", nargs="+", choices=list(MODULES), default=list(MODULES),
                    help="run in this order, one mutmut call each (default: all, the fast ones first)")
    ap.add_argument("--sample", type=int, default=0, help="mutants drawn per module (0: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-children", type=int, default=1, help="mutants checked at once (the build machine: 1)")
    ap.add_argument("--report-only", action="store_true", help="no mutmut run: the page from the results so far")
    ap.add_argument("--recheck-survivors", action="store_true",
                    help="run the survivors so far not listed as equivalent again (after tests were added), nothing else")
    ap.add_argument("--only", nargs="+", default=[], metavar="PATTERN",
                    help="with --recheck-survivors: only the survivors whose name matches one of these (fnmatch)")
    ap.add_argument("--output", type=Path, default=Path(tempfile.gettempdir()) / "mutation.md")
    ap.add_argument("--update-results", action="store_true", help="write docs/results/mutation.md")
    args = ap.parse_args()
    if not args.report_only and mutants_out_of_date(args.modules):
        run_mutmut(["__generate_only__"], args.max_children)  # every mutant and the test map; no name matches
    if args.recheck_survivors:
        # mutmut finds the tests added since its last run and maps which functions they reach before it runs
        again = []
        for m in args.modules:  # the equivalent ones would only survive again
            names = {k for k, v in meta_results(MODULES[m]).items()
                     if v is not None and v not in KILLED and k not in EQUIVALENT
                     and (not args.only or any(fnmatch.fnmatch(k, pat) for pat in args.only))}
            forget(MODULES[m], names)
            again += sorted(names)
        run_mutmut(again, args.max_children)
    elif not args.report_only:
        for m in args.modules:  # module by module; a mutant with a result is not run again (resumes a stopped run)
            results = meta_results(MODULES[m])
            keys = sorted(results)
            if args.sample and len(keys) > args.sample:
                keys = sorted(random.Random(f"{args.seed}:{m}").sample(keys, args.sample))
            todo = [k for k in keys if results[k] is None]
            if todo:
                run_mutmut(todo, args.max_children)
    rows, survivors = [], []
    for m in args.modules:
        results = meta_results(MODULES[m])
        checked = {k: v for k, v in results.items() if v is not None}
        killed = sum(v in KILLED for v in checked.values())
        rows.append({"module": m, "total": len(results), "checked": len(checked), "killed": killed,
                     "survived": len(checked) - killed,
                     "equivalent": sum(k in EQUIVALENT for k, v in checked.items() if v not in KILLED)})
        survivors += [(k, diff_of(k, MODULES[m])) for k, v in sorted(checked.items()) if v not in KILLED]
    command = "python bench/mutation_check.py " + " ".join(a for a in sys.argv[1:] if a != "--update-results")
    if args.report_only:
        command = ("nice -n 19 python bench/mutation_check.py (every mutant, module by module; resumes when stopped); "
                   "python bench/mutation_check.py --recheck-survivors (after the tests that kill survivors were "
                   "added); python bench/mutation_check.py --report-only")
    text = page(rows, survivors, command.strip())
    out = ROOT / "docs/results/mutation.md" if args.update_results else args.output
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text.split("## Survivors")[0])
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
