"""Fault injection of the board simulator, checked against the real stream decoder (no ROS, no pty).

The truth counters must predict ``StreamDecoder.stats`` exactly, for every fault kind together.
"""

from __future__ import annotations

import numpy as np
import pytest

from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, SYNC, Status
from fbg_accel_driver.stream_decoder import StreamDecoder
from fbg_accel_sim import faults as fz
from fbg_accel_sim.board_physics import BoardSimulator, SimConfig, simulate_recording

FAULTS = {
    "scenario.rate_hz": 500.0, "scenario.duration_s": 20.0,
    "faults.bit_flips.count": 25, "faults.dropped.count": 15, "faults.duplicated.count": 12, "faults.truncated.count": 20,
    "faults.garbage.count": 18, "faults.resets.at_s": [7.5, 13.0], "faults.disconnects.at_s": [16.0],
    "faults.disconnects.down_s": 0.4, "faults.bit_flips.at_s": [3.0], "faults.dropped.at_s": [3.0],  # collision: moved on
}


@pytest.mark.parametrize("seed", [0, 1])
def test_decoder_counts_equal_the_injected_faults(seed: int) -> None:
    sim = BoardSimulator(SimConfig.default().with_overrides(FAULTS), seed=seed)
    blk = sim.run(20.0, block=3001)  # odd block size: faults straddle block and chunk boundaries
    data = blk.wire_bytes()
    dec = StreamDecoder()
    frames = []
    for i in range(0, len(data), 777):  # arbitrary chunking of the byte stream
        frames += dec.feed(data[i:i + 777])
    s = dec.stats
    exp = sim.expected_decoder_stats()
    assert blk.injected_bit_flips == 26 and blk.injected_truncated == 20 and blk.injected_dropped == 16
    assert blk.injected_duplicates == 12 and blk.injected_garbage_bursts == 18 and blk.injected_resets == 2
    assert s.crc_errors == blk.injected_crc_errors == 46 == exp["crc_errors"]
    assert s.duplicates == exp["duplicates"] == 12
    assert s.resets == exp["resets"] == 2
    assert s.lost_frames == exp["lost_frames"]
    assert s.frames == exp["frames"] == len(frames)
    assert s.bytes_discarded == exp["bytes_discarded"]
    assert s.invalid_frames == 0 and s.unsupported_version == 0
    # every intact frame arrives once, in order, identical to what the simulator says it sent
    expected = [(f.seq, f.t_us, f.ref, f.x, f.y, f.z, f.temp_cc, f.status) for f in blk.frames()]
    dedup = [e for i, e in enumerate(expected) if i == 0 or e != expected[i - 1]]
    got = [(f.seq, f.t_us, f.ref, f.x, f.y, f.z, f.temp_cc, f.status) for f in frames]
    assert got == dedup
    # lost = dropped + corrupted + unsent (disconnect) except losses the decoder cannot see across a reset
    assert s.lost_frames <= blk.injected_dropped + blk.injected_crc_errors + blk.unsent_frames


def test_bit_flips_stay_in_the_body_and_garbage_never_contains_sync_bytes() -> None:
    c = SimConfig.default().with_overrides({"scenario.duration_s": 10.0, "faults.bit_flips.count": 40,
                                            "faults.garbage.count": 40})
    sim = BoardSimulator(c, seed=2)
    blk = sim.run(10.0)
    clean = BoardSimulator(c.with_overrides({"faults.bit_flips.count": 0, "faults.garbage.count": 0}), seed=2).run(10.0)
    flipped = np.flatnonzero(blk.wire_fault == fz.BIT_FLIP)
    assert len(flipped) == 40
    pieces, clean_pieces = blk.wire_pieces(), clean.wire_pieces()
    for i in flipped:
        piece = pieces[i][-FRAME_SIZE_V1:]
        orig = clean_pieces[i]
        diff = np.flatnonzero(np.frombuffer(piece, np.uint8) != np.frombuffer(orig, np.uint8))
        assert len(diff) == 1 and diff[0] >= fz.FLIP_FIRST_BYTE
        assert bin(piece[diff[0]] ^ orig[diff[0]]).count("1") == 1
    garbage = b"".join(p[: len(p) - FRAME_SIZE_V1] for p, g in zip(pieces, blk.garbage_before, strict=True) if g)
    assert len(garbage) == blk.injected_garbage_bytes and SYNC[0] not in garbage and SYNC[1] not in garbage


def test_board_reset_restarts_sequence_and_clock_with_boot_flag() -> None:
    c = SimConfig.default().with_overrides({"scenario.duration_s": 6.0, "faults.resets.at_s": [3.0]})
    blk = BoardSimulator(c, seed=0).run(6.0)
    sent = blk.sent
    boot = (blk.status & int(Status.BOOT)) != 0
    assert boot.sum() == 2 and boot[0]
    k = int(np.flatnonzero(boot)[1])
    assert blk.seq[k] == 0 and blk.t_us[k] < blk.t_us[k - 31] and (~sent).sum() == 30  # 0.3 s boot gap at 100 Hz
    assert blk.t_us[k] == pytest.approx(0.3e6, abs=2e4)


def test_boot_flag_is_on_the_first_frame_sent_after_a_reboot_the_link_was_down_for() -> None:
    """The board's writer discards frames while the link is down (SPP: no client, fbg_board.ino writer_task), and BOOT
    marks the first frame it delivers after power-up (docs/protocol.md section 4). A reboot after a short uptime, its
    first frames discarded, must still be a reset: its clock (2.5 s at the reconnection) is past the last frame of the
    previous boot (0.49 s), so only BOOT can tell."""
    c = SimConfig.default().with_overrides({"scenario.duration_s": 6.0, "faults.resets.at_s": [1.0],
                                            "faults.disconnects.at_s": [0.5, 4.0], "faults.disconnects.down_s": 3.0})
    sim = BoardSimulator(c, seed=0)
    blk = sim.run(6.0)
    boot = np.flatnonzero((blk.status & int(Status.BOOT)) != 0)
    # boot B: reset at 1.0 s, seq 0 at 1.3 s (after the boot gap), first sent at 3.5 s (seq 220, board clock 2.5 s);
    # sample indices one more than at exactly 100 Hz: the default board crystal runs 20 ppm fast (board.clock_ppm)
    assert boot.tolist() == [0, 351]
    assert blk.sent[boot].all() and blk.seq[351] == 220 and blk.t_us[351] == pytest.approx(2.5e6, abs=2e4)
    dec = StreamDecoder()
    frames = dec.feed(blk.wire_bytes())
    assert dec.stats.resets == sim.expected_decoder_stats()["resets"] == blk.injected_resets == 1
    assert dec.stats.lost_frames == sim.expected_decoder_stats()["lost_frames"] == 0
    assert [f.seq for f in frames if f.status & Status.BOOT] == [0, 220]


def test_adc_saturation_source_dropout_and_temperature_faults() -> None:
    c = SimConfig.default().with_overrides({
        "scenario.duration_s": 12.0, "effects.reference_dark_offset.scale": 0.0,
        "faults.adc_saturation.windows": [{"start_s": 1.0, "duration_s": 0.5, "channels": ["x", "z"]}],
        "faults.source_dropout.windows": [{"start_s": 3.0, "duration_s": 5.0, "level": 0.0}],
        "faults.temperature_invalid.windows": [{"start_s": 9.0, "duration_s": 1.0}],
        "faults.temperature_absent.windows": [{"start_s": 10.5, "duration_s": 1.0}],
        "faults.adc_overrun.windows": [{"start_s": 2.0, "duration_s": 0.1}]})
    blk = BoardSimulator(c, seed=0).run(12.0)
    t = blk.t_s
    sat = (t >= 1.0) & (t < 1.5)
    assert np.all(blk.x[sat] == 4095) and np.all(blk.z[sat] == 4095) and np.all(blk.saturated[sat][:, [1, 3]])
    assert not blk.saturated[~sat].any() and blk.saturated_samples == sat.sum()
    late = (t > 6.0) & (t < 8.0)  # the TIA (1 Hz) has settled: no light, no dark offset -> zero reference
    assert np.all(blk.ref[late] == 0) and np.all(blk.xyz[late] <= 6)  # axes: only detector/TIA noise (clipped at 0)
    assert np.all(blk.ref[t > 11.5] > 800)  # light back
    overrun = (blk.status & int(Status.ADC_OVERRUN)) != 0
    assert np.array_equal(overrun, (t >= 2.0) & (t < 2.1))
    inv = (t >= 9.0) & (t < 10.0)
    absent = (t >= 10.5) & (t < 11.5)
    assert not np.any(blk.status[inv] & int(Status.TEMP_VALID)) and np.all(blk.status[inv] & int(Status.TEMP_PRESENT))
    held = blk.temp_cc[np.flatnonzero(inv)[0] - 1]
    assert np.all(blk.temp_cc[inv] == held)  # the firmware repeats the last good reading
    assert not np.any(blk.status[absent] & int(Status.TEMP_PRESENT)) and np.all(blk.temp_cc[absent] == 0)
    rec = simulate_recording(c, seed=0)
    assert np.isnan(rec.temp_c[(rec.t_s >= 9.0) & (rec.t_s < 10.0)]).all()
    assert np.isfinite(rec.temp_c[rec.t_s < 8.9]).all()


def test_random_faults_need_a_finite_window() -> None:
    with pytest.raises(ValueError, match="finite window"):
        BoardSimulator(SimConfig.default().with_overrides({"faults.bit_flips.count": 3}), seed=0)


def test_unflagged_faults_of_the_temperature_reading_change_the_reading_only() -> None:
    """``faults.temperature_reading`` (issue 8): a step from at_s on, a frozen stretch repeating the last delivered value
    across a chunk boundary (block 3001), one read (0.5 s at 2 Hz) off by size_c; TEMP_VALID stays set and every count is
    the same as without the faults."""
    base = {"scenario.temperature.profile": [{"ramp_to_c": 33.4, "duration_s": 30.0}], "thermal.optics_time_constant_s": 2.0,
            "effects.thermal_lag.scale": 0.0}
    fault = {"steps": [{"at_s": 20.0, "step_c": 0.5}], "frozen": [{"start_s": 5.0, "duration_s": 8.0}],
             "spikes": {"at_s": [16.2], "size_c": 50.0}}
    clean = BoardSimulator(SimConfig.default().with_overrides(base), seed=0).run(30.0, block=3001)
    blk = BoardSimulator(SimConfig.default().with_overrides({**base, "faults.temperature_reading": fault}),
                         seed=0).run(30.0, block=3001)
    t = blk.t_s
    assert np.array_equal(blk.counts, clean.counts) and np.all(blk.status & int(Status.TEMP_VALID))
    frozen = (t >= 5.0) & (t < 13.0)
    assert np.all(blk.temp_cc[frozen] == clean.temp_cc[np.flatnonzero(frozen)[0] - 1])
    assert np.ptp(clean.temp_cc[frozen]) > 100  # the temperature did change meanwhile (>1 degC)
    spike = (t >= 16.0) & (t < 16.5)
    step = t >= 20.0
    rest = ~(frozen | spike | step)
    assert np.array_equal(blk.temp_cc[rest], clean.temp_cc[rest])
    assert np.all(blk.temp_cc[spike] - clean.temp_cc[spike] == 5000)
    assert np.all(blk.temp_cc[step] - clean.temp_cc[step] == 50)
