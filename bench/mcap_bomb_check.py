#!/usr/bin/env python3
"""Decompression-bomb MCAP files: the work of reading one, per MB of file, against the same recording without them.

Not a test (test_mcap_recovery checks what is skipped; this measures how long it takes). Each file is a short
recording (our writer, 60 samples, 0.6 s at 100 Hz) with chunk records spliced in after its header:

* ``ratio``: three zstd chunks of 298-300 MiB of zeros each (~29 kB; the file with the recording: 41 kB), i.e. 35 million
  9-byte records of opcode 0 that the reader once looped over in Python (extrapolated ~80 min a chunk);
* ``frame``: one zstd chunk whose header claims 1 kB while its frame declares 300 MiB;
* ``records``: one uncompressed chunk of 1 MiB of zeros (ratio 1: only the record check stops it).

The floor is the same recording without the bombs, read in the same run; the figure is the extra time per MB of
the bombs, s/MB, and the whole read per MB of file (the target: under 1 s of work per MB of file). Best of
``--repeats``.

Usage::

    .venv/bin/python bench/mcap_bomb_check.py                      # writes /tmp/mcap_bomb.json
    .venv/bin/python bench/mcap_bomb_check.py --update-results     # writes bench/results/mcap_bomb.json
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import tempfile
import time
from pathlib import Path

import zstandard

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine_info import machine  # noqa: E402

from fbg_accel_calibration.io import mcap_reader, mcap_writer  # noqa: E402


def chunk_record(data: bytes, compression: str, uncompressed_size: int) -> bytes:
    comp = compression.encode()
    body = (struct.pack("<QQQI", 1, 2, uncompressed_size, 0) + struct.pack("<I", len(comp)) + comp
            + struct.pack("<Q", len(data)) + data)
    return struct.pack("<BQ", 0x06, len(body)) + body


def zstd_zeros(n_mb: int) -> bytes:
    co = zstandard.ZstdCompressor(level=3).compressobj(size=n_mb << 20)
    block = bytes(1 << 20)
    return b"".join([co.compress(block) for _ in range(n_mb)]) + co.flush()


def bombs(kind: str) -> bytes:
    if kind == "ratio":
        return b"".join(chunk_record(zstd_zeros(n), "zstd", n << 20) for n in (300, 299, 298))
    if kind == "frame":
        return chunk_record(zstd_zeros(300), "zstd", 1024)
    return chunk_record(bytes(1 << 20), "", 1 << 20)


def read_s(path: Path, repeats: int) -> tuple[float, int, int]:
    """Best time to read every sample of ``path`` (s), the samples and the skipped stretches."""
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        src = mcap_reader.McapSampleStream(path)
        n = sum(len(b) for b in src.blocks(10_000, with_poses=False))
        best = min(best, time.perf_counter() - t)
    return best, n, len(src.report.skipped)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--output", type=Path, default=Path(tempfile.gettempdir()) / "mcap_bomb.json")
    ap.add_argument("--update-results", action="store_true", help="write bench/results/mcap_bomb.json")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    out = ROOT / "bench/results/mcap_bomb.json" if args.update_results else args.output
    with tempfile.TemporaryDirectory() as tmp:
        clean = Path(tmp) / "clean.mcap"
        with mcap_writer.RecordingWriter(clean, {"sensor_id": "bench"}) as w:
            for i in range(60):
                w.write_raw(1_000_000_000 + i * 10_000_000, 870.0 + i % 3, [1100.0, 1600.0 + i % 5, 1100.0],
                            temperature_c=25.0, temperature_valid=True, seq=i % 65536, board_time_s=i * 0.01)
        data = clean.read_bytes()
        header_end = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]
        floor_s, n_clean, _ = read_s(clean, args.repeats)
        rows = {}
        for kind in ("ratio", "frame", "records"):
            extra = bombs(kind)
            path = Path(tmp) / f"{kind}.mcap"
            path.write_bytes(data[:header_end] + extra + data[header_end:])
            t, n, skipped = read_s(path, args.repeats)
            mb = len(extra) / 1e6
            rows[kind] = {"file_bytes": path.stat().st_size, "bomb_bytes": len(extra), "read_s": round(t, 4),
                          "samples": n, "samples_clean": n_clean, "skipped": skipped,
                          "extra_s_per_mb": round(max(t - floor_s, 0.0) / mb, 4),
                          "read_s_per_mb_of_file": round(t / (path.stat().st_size / 1e6), 4)}
            r = rows[kind]
            print(f"{kind:8s} bombs {len(extra):8d} B  file {r['file_bytes']:8d} B  read {t:.3f} s (clean "
                  f"{floor_s:.3f} s; {r['read_s_per_mb_of_file']:.3f} s/MB of file)  extra {r['extra_s_per_mb']:.3f} "
                  f"s/MB  samples {n}/{n_clean}  skipped {skipped}")
    out.write_text(json.dumps({"machine": machine(), "floor_s": round(floor_s, 4), "files": rows}, indent=1) + "\n")
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
