"""Damaged but recoverable recordings (issue 11): a corrupt chunk is skipped and reported, not the end
of the file; a file cut anywhere, or finished over a half-written record, gives what it holds and no
traceback; a recording whose ``imu/raw`` has another type or an unparsable schema gets one line.

The damage is made on real recordings written by ``write_recording``; chunk positions are found by
walking the file's record framing here, independently of the reader under test.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from test_fit_streaming import make_run

from fbg_accel_calibration.io import mcap_records, mcap_writer
from fbg_accel_calibration.io.mcap_format import McapRecordingError
from fbg_accel_calibration.io.mcap_reader import McapSampleStream, read_recording
from fbg_accel_calibration.io.mcap_writer import write_recording
from fbg_accel_calibration.io.recording import Recording

pytestmark = pytest.mark.real_time  # waits on processes, ptys or DDS (test/conftest.py)

BIN = Path(sys.executable).parent
LEVELS_C = (15.0, 25.0, 35.0)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three temperature levels of ten poses in one file, as an imported multi-level CSV."""
    runs = [make_run(i, t, t0_s=i * 100.0) for i, t in enumerate(LEVELS_C)]
    for i, r in enumerate(runs):
        r.pose_id[r.pose_id >= 0] += 10 * i
    path = tmp_path_factory.mktemp("campaign") / "campaign.mcap"
    write_recording(path, Recording.concatenate(runs), {"sensor_id": "fbg-test"})
    return path


@pytest.fixture(scope="module")
def one_level(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One level of ten poses: 16 chunks and the same summary section as the campaign's in a third of its bytes (the
    file the cut test reads twice at each of ~420 cuts)."""
    path = tmp_path_factory.mktemp("one_level") / "one_level.mcap"
    write_recording(path, make_run(0, LEVELS_C[0]), {"sensor_id": "fbg-test"})
    return path


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of every top-level record after the magic, up to the footer."""
    out, pos = [], 8
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, length))
        if op == 0x02:
            break
        pos += 9 + length
    return out


def raw_stamps(path: Path) -> np.ndarray:
    """Log times of every imu/raw message, read by the mcap library itself (the truth)."""
    with open(path, "rb") as fh:
        messages = make_reader(fh).iter_messages(topics=["imu/raw", "/imu/raw"])
        return np.array([m.log_time for _, ch, m in messages], dtype=np.int64)


def stream_count(path: Path) -> tuple[int, mcap_records.FileReadReport]:
    src = McapSampleStream(path)
    n = sum(len(b) for b in src.blocks(1000, with_poses=False))
    return n, src.report


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "fbg-accel-calib"), *args], capture_output=True, text=True, timeout=300)


def test_a_flipped_bit_in_a_chunk_skips_that_chunk_only(campaign: Path, tmp_path: Path) -> None:
    data = bytearray(campaign.read_bytes())
    chunks = [(o, n) for o, op, n in records(bytes(data)) if op == 0x06]
    assert len(chunks) >= 10, len(chunks)
    off, length = chunks[len(chunks) // 2]
    start_ns, end_ns = struct.unpack_from("<QQ", data, off + 9)
    truth = raw_stamps(campaign)
    lost = int(((truth >= start_ns) & (truth <= end_ns)).sum())
    assert lost > 0
    data[off + 9 + length // 2] ^= 0x10  # one bit inside the compressed records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))

    rec = read_recording(bad)
    rep = rec.metadata["read_report"]
    assert rep["complete"] and len(rep["skipped"]) == 1
    skipped = rep["skipped"][0]
    assert skipped["messages"]["/imu/raw"] == lost and (skipped["start_ns"], skipped["end_ns"]) == (start_ns, end_ns)
    assert len(rec) == len(truth) - lost
    assert rec.t_s[-1] == read_recording(campaign).t_s[-1]  # the rest of the file after the bad chunk is there
    n, report = stream_count(bad)
    assert n == len(rec) and report.complete and [s.as_dict() for s in report.skipped] == rep["skipped"]

    out = tmp_path / "cal.yaml"
    res = run_cli("fit", str(bad), "-o", str(out))
    assert res.returncode == 0, res.stderr
    assert f"WARNING: {bad}: damaged data skipped, {lost} /imu/raw samples lost" in res.stderr
    assert "Traceback" not in res.stderr
    import yaml

    lo, hi = yaml.safe_load(out.read_text())["temperature_range_c"]
    assert lo < LEVELS_C[0] + 1 and hi > LEVELS_C[-1] - 1  # every temperature level still in the fit


def test_a_flipped_bit_in_a_chunk_length_resynchronises_on_the_next_chunk(campaign: Path, tmp_path: Path) -> None:
    data = bytearray(campaign.read_bytes())
    chunks = [(o, n) for o, op, n in records(bytes(data)) if op == 0x06]
    off, _ = chunks[3]
    data[off + 1 + 5] ^= 0x01  # a high byte of the length: the record now claims to run past the file
    bad = tmp_path / "framing.mcap"
    bad.write_bytes(bytes(data))
    rec = read_recording(bad)
    rep = rec.metadata["read_report"]
    assert rep["complete"] and len(rep["skipped"]) == 1 and "framing lost" in rep["skipped"][0]["reason"]
    truth = raw_stamps(campaign)
    assert 0 < len(truth) - len(rec) < len(truth) // 5  # one chunk and its index lost, not the rest
    assert stream_count(bad)[0] == len(rec)


def test_a_file_cut_anywhere_gives_what_it_holds_in_both_readers(one_level: Path, tmp_path: Path) -> None:
    data = one_level.read_bytes()
    recs = records(data)
    assert sum(op == 0x06 for _, op, _ in recs) > 10 and recs[-1][1] == 0x02  # many chunks, a summary, a footer
    last_chunk = max(o for o, op, _ in recs if op == 0x06)
    rng = np.random.default_rng(0)
    cuts = sorted({*range(last_chunk - 20, last_chunk + 60), *range(len(data) - 300, len(data)),
                   *rng.integers(9, len(data), 40).tolist()})
    cut = tmp_path / "cut.mcap"
    for at in cuts:
        cut.write_bytes(data[:at])
        try:
            n_mem = len(read_recording(cut))
        except McapRecordingError:
            n_mem = 0
        try:
            n_stream = stream_count(cut)[0]
        except McapRecordingError:
            n_stream = 0
        assert n_mem == n_stream, at


def test_a_footer_written_over_a_half_written_record_is_tolerated(campaign: Path, tmp_path: Path) -> None:
    """What an interrupted writer that still "finished" its file leaves: a chunk cut short, then a footer
    and the closing magic. The readers keep every complete chunk before it; fit exits 0, no traceback."""
    data = campaign.read_bytes()
    chunks = [(o, n) for o, op, n in records(data) if op == 0x06]
    off, length = chunks[-3]
    footer = struct.pack("<BQ", 0x02, 20) + struct.pack("<QQI", 0, 0, 0) + b"\x89MCAP0\r\n"
    bad = tmp_path / "half.mcap"
    bad.write_bytes(data[: off + 9 + length // 2] + footer)
    rec = read_recording(bad)
    truth = raw_stamps(campaign)
    kept = int((truth < struct.unpack_from("<Q", data, off + 9)[0]).sum())
    assert len(rec) == kept and stream_count(bad)[0] == kept
    res = run_cli("fit", str(bad), "-o", str(tmp_path / "cal.yaml"))
    assert res.returncode in (0, 2) and "Traceback" not in res.stderr, res.stderr


def _mcap_with_raw_schema(path: Path, schema_name: str, definition: bytes) -> None:
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name=schema_name, encoding="ros2msg", data=definition)
        cid = w.register_channel(topic="imu/raw", message_encoding="cdr", schema_id=sid)
        w.add_message(cid, log_time=1, data=b"\x00\x01\x00\x00" + bytes(40), publish_time=1)
        w.finish()


@pytest.mark.parametrize("schema,definition,expected", [
    ("sensor_msgs/msg/Imu", b"float64 x\n",
     "topic 'imu/raw' has type 'sensor_msgs/msg/Imu', expected 'sensor_msgs/msg/JointState'"),
    ("sensor_msgs/msg/JointState", b"this is -- not a message definition ]]\n",
     "schema 'sensor_msgs/msg/JointState' of topic 'imu/raw' cannot be parsed"),
])
def test_wrong_raw_type_or_malformed_schema_is_one_line(tmp_path: Path, schema: str, definition: bytes,
                                                        expected: str) -> None:
    path = tmp_path / "other.mcap"
    _mcap_with_raw_schema(path, schema, definition)
    with pytest.raises(McapRecordingError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        read_recording(path)
    with pytest.raises(McapRecordingError, match="imu/raw"):
        stream_count(path)
    res = run_cli("fit", str(path), "-o", str(tmp_path / "cal.yaml"))
    assert res.returncode == 2 and expected in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "cal.yaml").exists()


def _plain_run(path: Path, rec: Recording, chunk_bytes: int = mcap_writer.DEFAULT_CHUNK_BYTES) -> None:
    """``rec`` written as raw messages, uncompressed (a chunk's records can be cut in the bytes)."""
    with mcap_writer.RecordingWriter(path, {"sensor_id": "x"}, compression="none", chunk_bytes=chunk_bytes) as w:
        for i in range(len(rec)):
            w.write_raw(int(rec.t_s[i] * 1e9) + 1, rec.ref[i], rec.xyz[i].tolist(), temperature_c=rec.temp_c[i],
                        temperature_valid=True, seq=i, board_time_s=rec.t_s[i])


def _chunk_with_its_last_record_cut(data: bytes, off: int, length: int) -> bytes:
    """The uncompressed chunk record at ``off`` (body ``length`` bytes) with 37 bytes of its last record lost and
    its CRC written again over what is left: what an interrupted writer that still checksums leaves."""
    import zlib

    body = data[off + 9: off + 9 + length]
    clen = struct.unpack_from("<I", body, 28)[0]
    head, recs = body[:40 + clen], body[40 + clen:]
    assert struct.unpack_from("<I", head, 24)[0] != 0  # the writer checksums its chunks
    cut = recs[:len(recs) - 37]  # the last raw message record loses its tail
    new_body = (head[:16] + struct.pack("<QI", len(cut), zlib.crc32(cut)) + head[28:32 + clen]
                + struct.pack("<Q", len(cut)) + cut)
    return struct.pack("<BQ", 0x06, len(new_body)) + new_body


def test_a_checksummed_chunk_ending_in_a_half_record_keeps_the_records_before_it(tmp_path: Path) -> None:
    """An interrupted writer that still finished its file: its last chunk holds a record cut short, with a
    valid CRC over it, then the footer. Both readers keep every message before that record; ``fit`` says
    what happened instead of dying with ``struct.error``."""
    src = tmp_path / "plain.mcap"
    _plain_run(src, make_run(4, 25.0))
    data = src.read_bytes()
    off, _, length = [r for r in records(data) if r[1] == 0x06][-1]
    footer = struct.pack("<BQ", 0x02, 20) + struct.pack("<QQI", 0, 0, 0) + b"\x89MCAP0\r\n"
    bad = tmp_path / "half_record.mcap"
    bad.write_bytes(data[:off] + _chunk_with_its_last_record_cut(data, off, length) + footer)
    expected = len(raw_stamps(src)) - 1
    got = read_recording(bad)
    assert len(got) == expected
    assert any(s["offset"] == -1 for s in got.metadata["read_report"]["skipped"])
    assert stream_count(bad)[0] == expected
    res = run_cli("fit", str(bad), "-o", str(tmp_path / "cal.yaml"))
    assert res.returncode in (0, 2) and "Traceback" not in res.stderr and "struct" not in res.stderr, res.stderr
    assert "cut short" in res.stderr


def test_a_half_record_in_a_chunk_mid_file_loses_only_that_record(tmp_path: Path) -> None:
    """The same cut record in a chunk with intact chunks after it. The readers split several chunks at once; on
    the code before, the cut record was read on into the next chunk's bytes (one message kept with another chunk's
    bytes in its values) and the split stopped there, losing the messages of the chunks joined after it: both
    readers kept 883 of the 1742. Now no record is read across its chunk's end: only the cut message is lost, and
    every other one keeps its values."""
    src = tmp_path / "plain.mcap"
    rec = make_run(4, 25.0)
    _plain_run(src, rec, chunk_bytes=4096)
    data = src.read_bytes()
    chunks = [r for r in records(data) if r[1] == 0x06]
    assert len(chunks) > 10
    off, _, length = chunks[len(chunks) // 2]
    bad = tmp_path / "half_record_mid.mcap"
    bad.write_bytes(data[:off] + _chunk_with_its_last_record_cut(data, off, length) + data[off + 9 + length:])
    truth = raw_stamps(src)
    got = read_recording(bad)
    assert len(got) == len(truth) - 1
    assert any(s["offset"] == -1 for s in got.metadata["read_report"]["skipped"])
    assert stream_count(bad)[0] == len(truth) - 1
    lost = np.flatnonzero(~np.isin(np.round(rec.t_s * 1e9).astype(np.int64) + 1, np.round(got.t_s * 1e9).astype(np.int64) + 1))
    assert len(lost) == 1
    keep = np.delete(np.arange(len(rec)), lost)
    np.testing.assert_array_equal(got.xyz, rec.xyz[keep])
    np.testing.assert_array_equal(got.ref, rec.ref[keep])


def _chunk_record(data: bytes, compression: str, uncompressed_size: int) -> bytes:
    """A chunk record holding ``data`` compressed as ``compression`` that claims ``uncompressed_size`` bytes (CRC 0:
    not checked, as the spec allows)."""
    comp = compression.encode()
    body = (struct.pack("<QQQI", 1, 2, uncompressed_size, 0) + struct.pack("<I", len(comp)) + comp
            + struct.pack("<Q", len(data)) + data)
    return struct.pack("<BQ", 0x06, len(body)) + body


def _zstd_zeros(n_mb: int) -> bytes:
    """A zstd frame of ``n_mb`` MiB of zero bytes (~32 bytes of it per MiB), compressed a MiB at a time."""
    import zstandard

    co = zstandard.ZstdCompressor(level=3).compressobj(size=n_mb << 20)
    block = bytes(1 << 20)
    return b"".join([co.compress(block) for _ in range(n_mb)]) + co.flush()


def _bombs(kind: str) -> bytes:
    """Chunk records that would make a reader do work out of all proportion to their size: ``ratio``, three zstd
    chunks of 298-300 MiB of zeros (~29 kB in all: a 32 kB file with the run; the zeros are 35 million 9-byte records of
    opcode 0, a Python loop of ~80 min); ``frame``, a chunk whose header claims 1 kB while its zstd frame declares
    300 MiB (decompression allocates what the frame declares); ``records``, an uncompressed chunk of 1 MiB of zeros
    (ratio 1, but records no chunk can hold); ``summary``, the same chunk where the footer says the summary
    section starts (the mcap library, which reads the summary, expanded it into 116 000 records in Python)."""
    if kind == "ratio":
        return b"".join(_chunk_record(_zstd_zeros(n), "zstd", n << 20) for n in (300, 299, 298))
    if kind == "frame":
        return _chunk_record(_zstd_zeros(300), "zstd", 1024)
    return _chunk_record(bytes(1 << 20), "", 1 << 20)


@pytest.mark.parametrize("kind", ["ratio", "frame", "records", "summary"])
def test_a_decompression_bomb_chunk_is_skipped_with_its_reason(kind: str, tmp_path: Path) -> None:
    """A chunk that decompresses to far more than any recording's chunk (our writer's constant-data chunks: 15x), one
    whose zstd frame declares more than its header, or one of records a chunk cannot hold, is skipped as damaged data
    with the reason, before any per-record work: the recording around it reads as without it. Before, a 10 kB file
    made every command loop in Python over millions of 9-byte records (165 s for 10 MB of zeros; 731 MB RSS)."""
    src = tmp_path / "run.mcap"
    _plain_run(src, make_run(4, 25.0))
    data = src.read_bytes()
    header_end = 8 + 9 + records(data)[0][2]
    bombs = _bombs(kind)
    bad = tmp_path / "bomb.mcap"
    if kind == "summary":  # the footer's summary_start points at the chunk of zeros, appended after the data
        summary_at = len(data) - 8 - 9 - 20
        footer = bytearray(data[summary_at:])
        struct.pack_into("<Q", footer, 9, summary_at)
        bad.write_bytes(data[:summary_at] + bombs + bytes(footer))
    else:
        bad.write_bytes(data[:header_end] + bombs + data[header_end:])
    truth = read_recording(src)
    got = read_recording(bad)
    np.testing.assert_array_equal(got.xyz, truth.xyz)
    skipped = got.metadata["read_report"]["skipped"]
    assert len(skipped) == (3 if kind == "ratio" else 1), skipped
    reason = {"ratio": "decompression ratio", "frame": "zstd frame declares", "records": "opcode 0",
              "summary": "opcode 0"}[kind]
    assert all(reason in s["reason"] for s in skipped), skipped
    n, report = stream_count(bad)
    assert n == len(truth) and len(report.skipped) == len(skipped)


def test_an_exact_duplicate_chunk_is_read_once_with_a_note(tmp_path: Path) -> None:
    """A chunk written twice (a copy tool that repeated a block, a writer that retried a flush): its samples were
    fitted twice and the warning guessed "a driver restart or a clock step?". A chunk record equal byte for byte to
    one read before (in the file, or in an earlier file of the bag) is read once, and a note counts the copies."""
    src = tmp_path / "run.mcap"
    _plain_run(src, make_run(4, 25.0), chunk_bytes=4096)
    data = src.read_bytes()
    chunks = [r for r in records(data) if r[1] == 0x06]
    assert len(chunks) > 5
    (o1, _, n1), (o2, _, n2) = chunks[1], chunks[3]
    bad = tmp_path / "dup.mcap"
    # chunk 1 again right after itself, chunk 3 again at the end of the data section
    end = chunks[-1][0] + 9 + chunks[-1][2]
    bad.write_bytes(data[:o1 + 9 + n1] + data[o1:o1 + 9 + n1] + data[o1 + 9 + n1:end] + data[o2:o2 + 9 + n2]
                    + data[end:])
    truth = read_recording(src)
    got = read_recording(bad)
    np.testing.assert_array_equal(got.xyz, truth.xyz)
    np.testing.assert_array_equal(got.t_s, truth.t_s)
    notes = got.metadata["read_report"]["notes"]
    assert len(notes) == 1 and "2 chunks" in notes[0] and "exact copies" in notes[0] and "read once" in notes[0], notes
    n, report = stream_count(bad)
    assert n == len(truth) and report.notes == notes


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_run_s_limit_is_the_first_later_chunk_end_between_records_of_a_full_scan(seed: int) -> None:
    """Where a run of fixed-layout messages must stop (``_first_misaligned_end``, read in growing windows of the later
    chunk ends) is where a scan of every later end finds it: the first end that is not a whole number of records
    after the run's position, the file's size when there is none."""
    rng = np.random.default_rng(seed)
    rec_size = 57
    for _ in range(200):
        n = int(rng.integers(1, 700))
        step = np.where(rng.random(n) < rng.uniform(0.0, 0.05), rng.integers(1, 300, n), rec_size * rng.integers(1, 9, n))
        ends = np.cumsum(step)
        size = int(ends[-1])
        pos = int(rng.integers(0, size))
        later = ends[ends > pos]
        misaligned = np.flatnonzero((later - pos) % rec_size)
        want = int(later[misaligned[0]]) if misaligned.size else size
        assert mcap_records._first_misaligned_end(ends, pos, rec_size, size) == want
