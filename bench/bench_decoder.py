#!/usr/bin/env python3
"""Throughput of the pure-Python stream decoder (fbg_accel_driver.stream_decoder) on this machine.

Encodes N version-1 frames once, then times ``StreamDecoder.feed`` over the byte stream cut into
chunks of typical serial read sizes, for a clean stream and for a faulty one (garbage bursts, bit
flips, truncated and duplicated frames). Reports frames/s and microseconds per frame (best and
median of R repeats, wall clock, one core) and compares with the frame rate a 921600-baud 8N1 link
can carry (``link_frame_rate_limit``): ``headroom`` = decoder rate / link rate, and
``cpu_fraction_at_link_rate`` = link rate / decoder rate (share of one core the decoder needs to
keep up with a saturated link).

Usage::

    .venv/bin/python bench/bench_decoder.py                       # writes bench/results/decoder.json
    .venv/bin/python bench/bench_decoder.py --frames 50000 --repeats 3 --output /tmp/d.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from machine_info import results_doc, write_results  # noqa: E402
from output_paths import add_update_results, results_dir  # noqa: E402

from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, Frame, Status, encode_frame, link_frame_rate_limit  # noqa: E402
from fbg_accel_driver.stream_decoder import StreamDecoder  # noqa: E402

BAUD = 921600
CHUNK_SIZES = (64, 512, 4096)


def make_frames(n: int, seed: int = 0) -> list[Frame]:
    """``n`` frames of a 1 kHz stream with plausible 12-bit counts and AHT10 temperatures."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(500, 4096, (n, 4))
    temp = 2300 + np.cumsum(rng.integers(-1, 2, n))
    status = int(Status.TEMP_VALID | Status.TEMP_PRESENT)
    return [
        Frame(seq=i % 65536, t_us=1_000_000 + 1000 * i, ref=int(c[0]), x=int(c[1]), y=int(c[2]), z=int(c[3]),
              temp_cc=int(t), status=status)
        for i, (c, t) in enumerate(zip(counts, temp, strict=True))
    ]


def faulty_stream(frames: list[Frame], seed: int = 1) -> bytes:
    """About 1 % of frames bit-flipped, 0.5 % truncated, 0.5 % duplicated, 0.5 % followed by 20 garbage bytes."""
    rng = np.random.default_rng(seed)
    parts: list[bytes] = []
    for f in frames:
        enc = encode_frame(f)
        r = rng.random()
        if r < 0.01:
            bad = bytearray(enc)
            bad[int(rng.integers(4, FRAME_SIZE_V1))] ^= 0x20
            parts.append(bytes(bad))
        elif r < 0.015:
            parts.append(enc[: int(rng.integers(1, FRAME_SIZE_V1))])
        elif r < 0.02:
            parts += [enc, enc]
        elif r < 0.025:
            parts += [enc, rng.integers(0, 256, 20, dtype=np.uint8).tobytes()]
        else:
            parts.append(enc)
    return b"".join(parts)


def time_decode(stream: bytes, chunk: int, repeats: int) -> tuple[list[float], dict[str, int]]:
    """Wall-clock seconds of decoding ``stream`` fed in ``chunk``-byte pieces, ``repeats`` times."""
    pieces = [stream[i : i + chunk] for i in range(0, len(stream), chunk)]
    times = []
    stats: dict[str, int] = {}
    for _ in range(repeats):
        dec = StreamDecoder()
        n_out = 0
        t0 = time.perf_counter()
        for p in pieces:
            n_out += len(dec.feed(p))
        times.append(time.perf_counter() - t0)
        stats = dec.stats.as_dict()
        assert n_out == stats["frames"]
    return times, stats


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=200_000, help="frames per run (default 200000)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per case (default 5)")
    ap.add_argument("--output", type=Path, help="output file (default: decoder.json in the scratch or results directory)")
    add_update_results(ap)
    args = ap.parse_args(argv)
    args.output = args.output or results_dir(args.update_results) / "decoder.json"

    frames = make_frames(args.frames)
    streams = {"clean": b"".join(encode_frame(f) for f in frames), "faulty": faulty_stream(frames)}
    link_rate = link_frame_rate_limit(BAUD)
    results = []
    print(f"{'stream':8} {'chunk B':>8} {'frames/s (best)':>16} {'us/frame (best)':>16} {'us/frame (median)':>18} "
          f"{'x link limit':>13}")
    for name, stream in streams.items():
        for chunk in CHUNK_SIZES:
            times, stats = time_decode(stream, chunk, args.repeats)
            n = stats["frames"]
            best, med = min(times), statistics.median(times)
            row = {"stream": name, "chunk_bytes": chunk, "frames_decoded": n, "bytes": len(stream),
                   "seconds_best": best, "seconds_median": med, "frames_per_s_best": n / best, "frames_per_s_median": n / med,
                   "us_per_frame_best": 1e6 * best / n, "us_per_frame_median": 1e6 * med / n,
                   "headroom_vs_link_limit": (n / med) / link_rate, "cpu_fraction_at_link_rate": link_rate / (n / med),
                   "decoder_stats": stats}
            results.append(row)
            print(f"{name:8} {chunk:8d} {row['frames_per_s_best']:16.0f} {row['us_per_frame_best']:16.2f} "
                  f"{row['us_per_frame_median']:18.2f} {row['headroom_vs_link_limit']:13.1f}")
    doc = results_doc("bench_decoder.py", argv, "stream decoder throughput (StreamDecoder.feed, pure Python, one core, "
                      "wall clock)") | {
        "link": {"baud": BAUD, "frame_bytes": FRAME_SIZE_V1, "bits_per_byte": 10, "frames_per_s_limit": link_rate},
        "frames_per_run": args.frames, "repeats": args.repeats, "results": results}
    write_results(args.output, doc)
    print(f"link limit at {BAUD} baud: {link_rate:.1f} frames/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
