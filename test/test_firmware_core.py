"""The firmware's portable C core (firmware/core), built for the host and checked against the Python codec.

The host programs are compiled from source into a temporary directory by a module fixture (a
missing compiler fails with a clear message, see firmware_build.py):

* ``fbg_encode`` turns sample tuples into frames: byte-equal to ``frame_codec.encode_frame`` and
  decoded by ``StreamDecoder`` to the same values, for hypothesis-generated samples over the full
  field ranges, across the sequence wrap and the whole u64 clock range;
* ``fbg_board_host`` runs the firmware's sampling loop (scheduler, sequence counter, BOOT bit,
  AHT10 state machine) against a simulated clock and a simulated AHT10: its frames decode with
  every decoder counter exact, the read times follow the schedule with no drift over a simulated
  hour, and the AHT10 cases (absent, NACK, stuck busy, bad CRC-8, out of range, lost calibration,
  bus stuck high) give the temperature bits docs/protocol.md and docs/firmware.md promise.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from fractions import Fraction
from math import floor
from pathlib import Path

import pytest
from firmware_build import FirmwareHostPrograms, build_host_programs
from frame_strategies import frames as frame_strategy
from frame_strategies import frames_v2
from hypothesis import given, settings
from hypothesis import strategies as st

from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, FRAME_SIZE_V2, SEQ_MODULO, Frame, Status, encode_frame
from fbg_accel_driver.stream_decoder import StreamDecoder

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

TEMP_BITS = int(Status.TEMP_VALID | Status.TEMP_PRESENT)


@pytest.fixture(scope="module")
def fw(tmp_path_factory: pytest.TempPathFactory) -> FirmwareHostPrograms:
    return build_host_programs(tmp_path_factory.mktemp("firmware_host"))


def sample_line(f: Frame) -> str:
    aux = "" if f.aux is None else f" {f.aux}"
    return f"{f.seq} {f.t_us} {f.ref} {f.x} {f.y} {f.z} {f.temp_cc} {f.status}{aux}\n"


def run_encode(fw: FirmwareHostPrograms, frames: list[Frame]) -> bytes:
    res = subprocess.run([str(fw.fbg_encode)], input="".join(map(sample_line, frames)).encode(), capture_output=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr.decode()
    return res.stdout


def run_board(fw: FirmwareHostPrograms, *args: str) -> subprocess.CompletedProcess:
    res = subprocess.run([str(fw.fbg_board_host), *args], capture_output=True, timeout=120)
    assert res.returncode == 0, res.stderr.decode()
    return res


# ----------------------------------------------------------------------------- encoder
GOLDEN = (Frame(seq=0x1234, t_us=0x0102030405060708, ref=4095, x=2048, y=1, z=0, temp_cc=-1234, status=0x03),
          "a55a011534120807060504030201ff0f0008010000002efb0317ae")


def test_encoder_reproduces_the_protocol_test_vectors(fw: FirmwareHostPrograms) -> None:
    out = run_encode(fw, [GOLDEN[0], Frame(0, 0, 0, 0, 0, 0, 0, 0)])
    assert out.hex() == GOLDEN[1] + "a55a0115" + "00" * 21 + "82d4"  # docs/protocol.md section 3


@settings(max_examples=150, deadline=None)
@given(st.lists(frame_strategy, min_size=1, max_size=40))
def test_encoder_is_byte_equal_to_python_and_decodes_to_the_same_values(fw: FirmwareHostPrograms,
                                                                        frames: list[Frame]) -> None:
    out = run_encode(fw, frames)
    assert out == b"".join(encode_frame(f) for f in frames)
    for k, f in enumerate(frames):  # each frame alone: no sequence bookkeeping between unrelated samples
        decoded = StreamDecoder().feed(out[k * FRAME_SIZE_V1:(k + 1) * FRAME_SIZE_V1])
        assert decoded == [f]


@settings(max_examples=150, deadline=None)
@given(st.lists(st.one_of(frame_strategy, frames_v2), min_size=1, max_size=40))
def test_version2_encoder_is_byte_equal_to_python_in_mixed_streams(fw: FirmwareHostPrograms, frames: list[Frame]) -> None:
    """Protocol version 2 (aux channel, docs/protocol.md): the C encoder writes what frame_codec writes, for
    v1 and v2 frames interleaved, and each frame decodes back to itself (aux included)."""
    out = run_encode(fw, frames)
    assert out == b"".join(encode_frame(f) for f in frames)
    pos = 0
    for f in frames:
        size = FRAME_SIZE_V1 if f.aux is None else FRAME_SIZE_V2
        assert StreamDecoder().feed(out[pos:pos + size]) == [f]
        pos += size
    assert pos == len(out)


@st.composite
def board_streams(draw: st.DrawFn) -> list[Frame]:
    """Consecutive samples of one boot: seq from anywhere (often just before the wrap), t_us strictly
    increasing from anywhere in the u64 range, temperature bits and ADC counts arbitrary. The clock advances by
    about one sample interval per seq (a nominal interval up to 2^31 us, each step up to half of it longer), as
    the firmware's scheduler does: the decoder counts whole wraps of seq in a t_us step far longer than that."""
    n = draw(st.integers(2, 60))
    seq0 = draw(st.one_of(st.integers(SEQ_MODULO - n, SEQ_MODULO - 1), st.integers(0, SEQ_MODULO - 1)))
    dt0 = draw(st.integers(1, 2**31))
    steps = [dt0 + draw(st.integers(0, dt0 // 2)) for _ in range(n - 1)]
    t0 = draw(st.integers(0, 2**64 - 1 - sum(steps)))
    adc = st.integers(0, 4095)
    out, t = [], t0
    for k in range(n):
        status = draw(st.integers(0, 7)) | (int(Status.BOOT) if k == 0 and draw(st.booleans()) else 0)
        out.append(Frame((seq0 + k) % SEQ_MODULO, t, draw(adc), draw(adc), draw(adc), draw(adc),
                         draw(st.integers(-(2**15), 2**15 - 1)), status))
        if k < n - 1:
            t += steps[k]
    return out


@settings(max_examples=100, deadline=None)
@given(board_streams())
def test_encoded_stream_decodes_with_every_counter_exact_across_wrap_and_clock_range(fw: FirmwareHostPrograms,
                                                                                       frames: list[Frame]) -> None:
    out = run_encode(fw, frames)
    dec = StreamDecoder()
    assert dec.feed(out) == frames
    assert dec.stats.as_dict() == {"frames": len(frames), "bytes_received": len(out), "bytes_discarded": 0,
                                   "crc_errors": 0, "invalid_frames": 0, "unsupported_version": 0,
                                   "lost_frames": 0, "duplicates": 0, "resets": 0}


@pytest.mark.parametrize(("line", "field"), [
    ("1 2 3 4 5 6 7", "'status' missing"),
    ("65536 0 0 0 0 0 0 0", "'seq' is not an integer in 0..65535"),
    ("0 18446744073709551616 0 0 0 0 0 0", "'t_us'"),
    ("0 0 4096 0 0 0 0 0", "'ref' is not an integer in 0..4095"),
    ("0 0 0 0 0 -1 0 0", "'z'"),
    ("0 0 0 0 0 0 32768 0", "'temp_cc' is not an integer in -32768..32767"),
    ("0 0 0 0 0 0 0 256", "'status'"),
    ("0 0 0 0 0 0 0 0 9 1", "more than 9 fields"),
    ("0 0 0 0 0 0 0 0 4096", "'aux' is not an integer in 0..4095"),
    ("0 0 0x10 0 0 0 0 0", "'ref'"),
])
def test_encoder_rejects_bad_lines_naming_line_and_field(fw: FirmwareHostPrograms, line: str, field: str) -> None:
    good = sample_line(GOLDEN[0])
    res = subprocess.run([str(fw.fbg_encode)], input=f"# comment\n{good}\n{line}\n{good}".encode(), capture_output=True,
                         timeout=60)
    err = res.stderr.decode()
    assert res.returncode == 2, err
    assert err.count("\n") == 1 and err.startswith("fbg_encode: error: stdin line 4: ") and field in err, err
    assert res.stdout == encode_frame(GOLDEN[0])  # the frame before the bad line was written, nothing after it


# ----------------------------------------------------------------------------- board loop: sequence, BOOT, clock
def synthetic_adc(k: int) -> tuple[int, int, int, int]:
    """The counts fbg_board_host's synthetic ADC returns for read k (see synthetic_adc() there)."""
    return 800 + k % 100, (7 * k) % 4096, (13 * k + 1000) % 4096, 4095 - k % 4096


@pytest.mark.parametrize("aux", [False, True], ids=["v1", "v2_aux"])
def test_board_loop_frames_decode_exactly_across_the_sequence_wrap(fw: FirmwareHostPrograms, aux: bool) -> None:
    """With ``--aux`` the loop reads a fifth channel and sends protocol-version-2 frames (docs/protocol.md)."""
    n = 70_000  # 70 s at 1 kHz: the u16 sequence wraps once
    out = run_board(fw, "--rate-mhz", "1000000", "--samples", str(n), *(["--aux"] if aux else [])).stdout
    dec = StreamDecoder()
    frames = dec.feed(out)
    size = FRAME_SIZE_V2 if aux else FRAME_SIZE_V1
    assert [f.aux for f in frames] == ([(29 * k + 7) % 4096 for k in range(n)] if aux else [None] * n)
    assert dec.stats.as_dict() == {"frames": n, "bytes_received": n * size, "bytes_discarded": 0,
                                   "crc_errors": 0, "invalid_frames": 0, "unsupported_version": 0,
                                   "lost_frames": 0, "duplicates": 0, "resets": 0}
    assert [f.seq for f in frames] == [k % SEQ_MODULO for k in range(n)]
    assert [f.t_us for f in frames] == [1000 * k for k in range(n)]
    assert [(f.ref, f.x, f.y, f.z) for f in frames] == [synthetic_adc(k) for k in range(n)]
    boot = [k for k, f in enumerate(frames) if f.status & Status.BOOT]
    assert boot == [0]
    assert not any(f.status & Status.ADC_OVERRUN for f in frames)
    assert all(f.status & 0xF0 == 0 for f in frames)


@dataclass(frozen=True)
class TimesLine:
    k: int
    seq: int
    t_us: int
    status: int


def board_times(fw: FirmwareHostPrograms, *args: str) -> tuple[list[TimesLine], str]:
    lines = run_board(fw, "--output", "times", *args).stdout.decode().splitlines()
    assert lines[-1].startswith("END ")
    return [TimesLine(*map(int, ln.split())) for ln in lines[:-1]], lines[-1]


@pytest.mark.parametrize("rate_mhz", [100_000, 1_000_000, 333_333])  # 100 Hz, 1 kHz, and a period of 3000.003 us
def test_scheduler_read_times_do_not_drift_over_a_simulated_hour(fw: FirmwareHostPrograms, rate_mhz: int) -> None:
    hour_us = 3600 * 10**6
    every = 997  # a prime stride, so the checked reads fall at every phase of a non-integer period
    lines, end = board_times(fw, "--rate-mhz", str(rate_mhz), "--duration-us", str(hour_us), "--every", str(every))
    # The reads due before the end of the hour: k with floor(k * 10^9 / rate) < hour.
    n_expected = -(-hour_us * rate_mhz // 10**9)
    assert end == f"END samples={n_expected} skipped=0"
    assert lines[-1].k == n_expected - 1 and len(lines) == (n_expected - 1) // every + 2
    for ln in lines:
        ideal = Fraction(ln.k * 10**9, rate_mhz)  # exact read time, us
        assert ln.t_us == floor(ideal) and 0 <= ideal - ln.t_us < 1, ln  # on the grid, less than 1 us behind
        assert ln.seq == ln.k % SEQ_MODULO and not ln.status & Status.ADC_OVERRUN


def test_late_read_is_flagged_and_a_long_stall_skips_reads_counted_as_lost(fw: FirmwareHostPrograms) -> None:
    # 100 Hz: read 10 starts 15 ms late (past read 11's time): ADC_OVERRUN, then read 11 catches up at once.
    lines, end = board_times(fw, "--samples", "15", "--late", "10:15000")
    assert end == "END samples=15 skipped=0"
    by_k = {ln.k: ln for ln in lines}
    assert by_k[10].t_us == 115_000 and by_k[10].status & Status.ADC_OVERRUN
    assert by_k[11].t_us == 115_040 and not by_k[11].status & Status.ADC_OVERRUN  # 40 us after: the default read cost
    assert by_k[12].t_us == 120_000 and [ln.seq for ln in lines] == list(range(15))
    assert [k for k, ln in by_k.items() if ln.status & Status.ADC_OVERRUN] == [10]
    # A 55 ms stall: 5 reads already due, more than the 4 the scheduler catches up: skipped, and the
    # sequence jumps by 5 so the host counts them as lost.
    out = run_board(fw, "--samples", "20", "--late", "10:55000").stdout
    dec = StreamDecoder()
    frames = dec.feed(out)
    assert [f.seq for f in frames] == [*range(11), *range(16, 25)]
    assert frames[10].t_us == 155_000 and frames[10].status & Status.ADC_OVERRUN
    assert [f.t_us for f in frames[11:]] == [10_000 * k for k in range(16, 25)]
    assert dec.stats.lost_frames == 5 and dec.stats.resets == 0 and dec.stats.frames == 20


# ----------------------------------------------------------------------------- link: BOOT on the first DELIVERED frame
# The SPP writer discards every frame while no client is connected (firmware/esp32/fbg_board/fbg_board.ino,
# writer_task), so BOOT must mark the first frame the writer actually sends after power-up (fbg_link_on_send in
# firmware/core/fbg_board.c), not the first sample produced: otherwise it is discarded with the others and a reboot
# after a short uptime is invisible to the host. fbg_board_host models the link with --link-connect-us US (frames
# produced before board time US are discarded) and --link-down-us A:B (discarded while A <= t_us < B).
@pytest.mark.parametrize("connect_us, aux", [(0, False), (5_000_000, False), (5_004_321, False), (2_500_000, True)],
                         ids=["at_power_up", "after_5s", "between_reads", "v2_aux"])
def test_first_frame_delivered_after_power_up_carries_boot_whatever_was_discarded(
        fw: FirmwareHostPrograms, connect_us: int, aux: bool) -> None:
    n = 1000  # 10 s at 100 Hz
    out = run_board(fw, "--samples", str(n), "--link-connect-us", str(connect_us), *(["--aux"] if aux else [])).stdout
    dec = StreamDecoder()
    frames = dec.feed(out)
    first = -(-connect_us // 10_000)  # the first read at or after the connection (reads at 10 ms * k)
    assert [f.seq for f in frames] == list(range(first, n)) and frames[0].t_us == 10_000 * first
    assert [k for k, f in enumerate(frames) if f.status & Status.BOOT] == [0]  # CRC recomputed: the decoder took it
    assert dec.stats.frames == n - first and dec.stats.crc_errors == 0 and dec.stats.bytes_discarded == 0
    assert dec.stats.lost_frames == 0 and dec.stats.resets == 0
    assert [(f.ref, f.x, f.y, f.z) for f in frames] == [synthetic_adc(k) for k in range(first, n)]
    lines, end = board_times(fw, "--samples", str(n), "--link-connect-us", str(connect_us))
    assert end == f"END samples={n} skipped=0"  # the sampler ran from power-up, whatever the link did
    assert [ln.seq for ln in lines] == list(range(first, n))  # times: the delivered samples, with the status sent
    assert [ln.seq for ln in lines if ln.status & Status.BOOT] == [first]


def test_reconnect_within_one_boot_carries_no_boot_and_its_gap_is_lost(fw: FirmwareHostPrograms) -> None:
    # client from 1 s, link down 3 s..4.5 s and 6 s..6.005 s (one read), the frames in between discarded
    out = run_board(fw, "--samples", "800", "--link-connect-us", "1000000", "--link-down-us", "3000000:4500000",
                    "--link-down-us", "6000000:6000005").stdout
    dec = StreamDecoder()
    frames = dec.feed(out)
    seqs = [*range(100, 300), *range(450, 600), *range(601, 800)]
    assert [f.seq for f in frames] == seqs
    assert [f.seq for f in frames if f.status & Status.BOOT] == [100]
    assert (dec.stats.resets, dec.stats.lost_frames, dec.stats.frames) == (0, 151, len(seqs))


def test_link_that_never_connects_sends_nothing(fw: FirmwareHostPrograms) -> None:
    assert run_board(fw, "--samples", "50", "--link-connect-us", "500000").stdout == b""


def test_reboot_after_a_short_uptime_over_spp_is_a_reset_and_stamps_stay_true(fw: FirmwareHostPrograms) -> None:
    """Brown-out with the host connected, the new boot's first frames discarded until the client is back: the host
    must count one reset and no loss, and stamp the new boot's samples at their true time (not 8.3 s early, the
    reboot's time shift read as transport delay, as when the BOOT frame was discarded)."""
    from test_driver_core import make_cal

    from fbg_accel_driver.driver_core import DriverCore

    h0 = 1_700_000_000_000_000_000
    # boot A: client from board 5 s, brown-out at 8 s; boot B starts 0.3 s later, client back at its board 10 s
    a = run_board(fw, "--duration-us", "8000000", "--link-connect-us", "5000000").stdout
    b = run_board(fw, "--duration-us", "40000000", "--link-connect-us", "10000000").stdout
    fa, fb = StreamDecoder().feed(a), StreamDecoder().feed(b)
    assert (fa[0].seq, fb[0].seq) == (500, 1000) and fa[0].status & Status.BOOT and fb[0].status & Status.BOOT
    pieces = [(a[i * FRAME_SIZE_V1:(i + 1) * FRAME_SIZE_V1], h0 + f.t_us * 1000) for i, f in enumerate(fa)]
    pieces += [(b[i * FRAME_SIZE_V1:(i + 1) * FRAME_SIZE_V1], h0 + 8_300_000_000 + f.t_us * 1000)
               for i, f in enumerate(fb)]
    core = DriverCore(make_cal())
    stamps = []
    for data, true_ns in pieces:
        stamps += [r.stamp_ns for r in core.feed(data, true_ns + 2_000_000).raw]  # 2 ms transport delay
    stamps += [r.stamp_ns for r in core.flush().raw]
    assert (core.decoder.stats.resets, core.decoder.stats.lost_frames, core.counters.board_resets) == (1, 0, 1)
    assert len(stamps) == len(pieces)
    worst = max(abs(s - t) for s, (_, t) in zip(stamps, pieces, strict=True))
    assert worst < 50_000_000, worst / 1e9


# ----------------------------------------------------------------------------- AHT10 state machine
@dataclass(frozen=True)
class AhtEvent:
    t_us: int
    reason: str  # a measurement outcome, or "state" for a change of the frames' temperature state alone
    raw: int
    temp_cc: int
    bits: int


def run_aht(fw: FirmwareHostPrograms, duration_s: float, *args: str) -> tuple[list[Frame], list[AhtEvent]]:
    res = run_board(fw, "--duration-us", str(int(duration_s * 1e6)), "--aht-log", *args)
    dec = StreamDecoder()
    frames = dec.feed(res.stdout)
    assert dec.stats.frames == len(frames) == len(res.stdout) // FRAME_SIZE_V1 and dec.stats.lost_frames == 0
    events = []
    for ln in res.stderr.decode().splitlines():
        tag, t, reason, raw, cc, bits = ln.split()
        assert tag == "AHT", ln
        events.append(AhtEvent(int(t), reason, int(raw), int(cc), int(bits)))
    return frames, events


def assert_frames_follow_the_state_machine(frames: list[Frame], events: list[AhtEvent]) -> None:
    """Every frame carries the temperature state after the last AHT10 event at or before its t_us."""
    j, bits, cc = 0, 0, 0
    for f in frames:
        while j < len(events) and events[j].t_us <= f.t_us:
            bits, cc = events[j].bits, events[j].temp_cc
            j += 1
        assert (f.status & TEMP_BITS, f.temp_cc) == (bits, cc), (f, events[max(j - 1, 0)])


def raw_to_cc(raw: int) -> int:
    """AHT10 datasheet: T = S_T / 2^20 * 200 - 50 degC, in 0.01 degC rounded half up (docs/firmware.md)."""
    return floor(Fraction(raw * 20000, 2**20) + Fraction(1, 2)) - 5000


def device_raw(cc: int) -> int:
    """S_T the simulated AHT10 reports for a temperature in 0.01 degC: floor((T + 50) / 200 * 2^20)."""
    return floor(Fraction((cc + 5000) * 2**20, 20000))


def test_aht10_readings_are_converted_to_centidegrees_and_carried_in_every_frame(fw: FirmwareHostPrograms) -> None:
    slope = 37  # 0.37 degC/s ramp of the simulated sensor
    frames, events = run_aht(fw, 6.0, "--temp-start-cc", "-3950", "--temp-slope-cc-per-s", str(slope))
    readings = [e for e in events if e.reason != "state"]
    assert [e.reason for e in readings] == ["ok"] * 12  # one per 500 ms period
    for e in readings:
        assert e.temp_cc == raw_to_cc(e.raw) and e.bits == TEMP_BITS
        trigger_us = e.t_us - 80_000  # read 80 ms after the trigger (fbg_aht10_default_config)
        assert e.raw == device_raw(-3950 + slope * trigger_us // 10**6)
    assert events[0] == AhtEvent(40_000, "state", 0, 0, int(Status.TEMP_PRESENT))  # answered the init at 40 ms
    assert_frames_follow_the_state_machine(frames, events)
    assert frames[0].status == Status.BOOT and frames[0].temp_cc == 0  # nothing known before the power-up wait
    assert not any(f.status & TEMP_BITS == Status.TEMP_VALID for f in frames)  # VALID never without PRESENT


def test_aht10_conversion_matches_the_datasheet_formula_over_the_whole_range(fw: FirmwareHostPrograms) -> None:
    # The simulated sensor sweeps -41..92 degC in 30 s: 60 readings across the range and past both ends.
    frames, events = run_aht(fw, 30.0, "--temp-start-cc", "-4100", "--temp-slope-cc-per-s", "450")
    readings = [e for e in events if e.reason != "state"]
    assert all(e.temp_cc == raw_to_cc(e.raw) for e in readings if e.reason == "ok")
    assert all((e.reason == "ok") == (-4000 <= raw_to_cc(e.raw) <= 8500) for e in readings)
    assert [e.reason for e in readings[:1]] == ["out_of_range"] and readings[-1].reason == "out_of_range"
    ok = [e.temp_cc for e in readings if e.reason == "ok"]
    assert len(ok) > 50 and min(ok) < -3800 and max(ok) > 8200
    assert_frames_follow_the_state_machine(frames, events)


def test_absent_sensor_clears_present_and_valid_and_sends_zero(fw: FirmwareHostPrograms) -> None:
    frames, events = run_aht(fw, 2.0, "--aht", "absent")
    assert events == [AhtEvent(60_000, "absent", 0, 0, 0)]  # three init attempts, 10 ms apart, after 40 ms
    assert all(f.status & TEMP_BITS == 0 and f.temp_cc == 0 for f in frames)


def test_aht10_faults_clear_temp_valid_keep_the_last_value_and_recover(fw: FirmwareHostPrograms) -> None:
    # Readings are triggered at 0.05 s + 0.5 s * n and read 80 ms later (busy: polled until 200 ms after the trigger).
    windows = {"nack": (1.0, 1.6), "busy": (2.5, 3.0), "range": (4.0, 4.5), "uncal": (5.5, 6.0), "ones": (7.0, 7.5)}
    reason = {"nack": "nack", "busy": "stuck", "range": "out_of_range", "uncal": "uncalibrated", "ones": "bus_stuck"}
    args = [a for kind, (t0, t1) in windows.items() for a in ("--aht-fault", f"{kind}:{int(t0 * 1e6)}:{int(t1 * 1e6)}")]
    frames, events = run_aht(fw, 9.0, "--temp-slope-cc-per-s", "37", *args)
    readings = [e for e in events if e.reason != "state"]
    for kind, (t0, t1) in windows.items():
        inside = [e for e in readings if t0 * 1e6 <= e.t_us <= t1 * 1e6]
        assert inside and {e.reason for e in inside} == {reason[kind]}, (kind, inside)
        after = next(e for e in readings if e.t_us > t1 * 1e6)
        assert after.reason == "ok" and after.bits == TEMP_BITS, (kind, after)  # recovers on the next period
    last_good = 0
    for e in readings:
        if e.reason == "ok":
            last_good = e.temp_cc
        else:  # failed reading: VALID cleared, PRESENT kept, last good value kept
            assert e.bits == Status.TEMP_PRESENT and e.temp_cc == last_good, e
    assert_frames_follow_the_state_machine(frames, events)
    invalid = [f for f in frames if f.status & TEMP_BITS == Status.TEMP_PRESENT and f.t_us > 1_000_000]
    assert len(invalid) > 200  # the faults did reach the frames


def test_aht20_crc8_is_checked_and_a_bad_crc_invalidates_the_reading(fw: FirmwareHostPrograms) -> None:
    frames, events = run_aht(fw, 3.0, "--aht", "aht20", "--aht-fault", "badcrc:1000000:2000000")
    readings = [e for e in events if e.reason != "state"]
    assert [(e.t_us, e.reason) for e in readings] == [
        (130_000, "ok"), (630_000, "ok"), (1_130_000, "bad_crc"), (1_630_000, "bad_crc"), (2_130_000, "ok"),
        (2_630_000, "ok")]
    assert_frames_follow_the_state_machine(frames, events)
    # The same corrupted byte on an AHT10 (6-byte read, no CRC) goes unnoticed: the check is AHT20-only.
    _, events10 = run_aht(fw, 3.0, "--aht", "aht10", "--aht-fault", "badcrc:1000000:2000000")
    assert {e.reason for e in events10} == {"ok", "state"}


def test_board_host_rejects_bad_options(fw: FirmwareHostPrograms) -> None:
    for args, what in ((["--samples", "10", "--rate-mhz", "0"], "--rate-mhz"), (["--bogus", "1"], "unknown option"),
                       (["--samples", "1", "--aht-fault", "heat:0:1"], "KIND"), ([], "exactly one of"),
                       (["--samples", "1", "--link-down-us", "5:1"], "--link-down-us"),
                       (["--samples", "1", "--link-connect-us", "-1"], "--link-connect-us")):
        res = subprocess.run([str(fw.fbg_board_host), *args], capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and res.stderr.count("\n") == 1 and what in res.stderr, (args, res.stderr)


def test_missing_compiler_fails_with_a_clear_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import firmware_build

    monkeypatch.setenv("CC", "no-such-compiler")
    monkeypatch.setattr(firmware_build.shutil, "which", lambda name: None)
    with pytest.raises(AssertionError, match="no C compiler found"):
        firmware_build.build_host_programs(tmp_path)


def test_docs_link_budget_table_is_the_scripts_output() -> None:
    """docs/firmware.md shows the numbers firmware/link_budget.py computes (no hand-edited figures)."""
    from firmware_build import REPO

    res = subprocess.run([sys.executable, str(REPO / "firmware" / "link_budget.py")], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() in (REPO / "docs" / "firmware.md").read_text()
    assert "| 1000 | 27,000 | 270,000 | 29.3 % |" in res.stdout  # 27 B x 1 kHz x 10 bit / 921600 baud
