"""Link budget of the board's output link: protocol-v1 frames per second against USB serial and Bluetooth SPP.

Prints a Markdown table (the one in docs/firmware.md) or, with ``--json``, the same numbers as JSON::

    .venv/bin/python firmware/link_budget.py
    .venv/bin/python firmware/link_budget.py --rates 100 1000 3000 --json

USB serial: UART 8N1, 10 bit times per byte (docs/protocol.md section 1), so a frame costs
``10 * 27`` bit times and the link carries ``baud / 270`` frames/s.

Bluetooth SPP: the RFCOMM payload has no start/stop bits (8 bits per byte). The throughput figure
is *documented, not measured here*: Espressif's ESP-FAQ, "What is the maximum transmission rate
for ESP32 Classic Bluetooth SPP?" answers "1400+ Kbps ~ 1590 Kbps (only for reference ...)" in an
open environment with simultaneous bidirectional transfer
(https://docs.espressif.com/projects/esp-faq/en/latest/software-framework/bt/br-edr.html). The
lower end, 1400 kbit/s, is used. Range, interference, the host's Bluetooth adapter and BlueZ can
reduce it by a large factor; measure your own link before relying on the headroom.
"""

from __future__ import annotations

import argparse
import json
import sys

from fbg_accel_driver.frame_codec import FRAME_SIZE_V1, link_frame_rate_limit

USB_BAUD = 921_600  # the driver's default `baud` and the firmware's FBG_USB_BAUD
UART_BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
SPP_DOCUMENTED_BPS = 1_400_000  # ESP-FAQ (Espressif), lower end of "1400+ Kbps ~ 1590 Kbps"; not measured here
SPP_BITS_PER_BYTE = 8
DEFAULT_RATES_HZ = (10.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 3000.0)


def budget(rate_hz: float) -> dict[str, float]:
    """Link load at ``rate_hz`` frames/s: payload in bytes/s and the fraction of each link it uses."""
    bytes_per_s = FRAME_SIZE_V1 * rate_hz
    return {
        "rate_hz": rate_hz,
        "bytes_per_frame": FRAME_SIZE_V1,
        "bytes_per_s": bytes_per_s,
        "usb_bit_times_per_s": bytes_per_s * UART_BITS_PER_BYTE,
        "usb_load": bytes_per_s * UART_BITS_PER_BYTE / USB_BAUD,
        "spp_bits_per_s": bytes_per_s * SPP_BITS_PER_BYTE,
        "spp_load": bytes_per_s * SPP_BITS_PER_BYTE / SPP_DOCUMENTED_BPS,
    }


def limits() -> dict[str, float]:
    """Highest frame rate each link carries at 100 % load, frames/s."""
    return {
        "usb_max_rate_hz": link_frame_rate_limit(USB_BAUD, FRAME_SIZE_V1, UART_BITS_PER_BYTE),
        "spp_max_rate_hz": SPP_DOCUMENTED_BPS / (SPP_BITS_PER_BYTE * FRAME_SIZE_V1),
    }


def markdown(rates: list[float]) -> str:
    """The link budget as a Markdown table plus the two limits."""
    lines = [
        "| rate (Hz) | bytes/s | USB serial 921600 baud: bit times/s | USB load "
        "| SPP payload bit/s | SPP load (1400 kbit/s documented) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rates:
        b = budget(r)
        lines.append(f"| {r:g} | {b['bytes_per_s']:,.0f} | {b['usb_bit_times_per_s']:,.0f} | {100 * b['usb_load']:.1f} % "
                     f"| {b['spp_bits_per_s']:,.0f} | {100 * b['spp_load']:.1f} % |")
    lim = limits()
    lines.append("")
    lines.append(f"Frame: {FRAME_SIZE_V1} bytes. Limits at 100 % load: USB serial {lim['usb_max_rate_hz']:.1f} frames/s, "
                 f"SPP {lim['spp_max_rate_hz']:.1f} frames/s (documented figure, not measured).")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="link_budget", description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=list(DEFAULT_RATES_HZ), help="sample rates in Hz")
    p.add_argument("--json", action="store_true", help="print JSON instead of the Markdown table")
    args = p.parse_args(argv)
    if any(not r > 0 for r in args.rates):
        print("link_budget: error: --rates must all be positive (Hz)", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"rows": [budget(r) for r in args.rates], **limits(), "usb_baud": USB_BAUD,
                          "spp_documented_bps": SPP_DOCUMENTED_BPS}, indent=2))
    else:
        print(markdown(args.rates))
    return 0


if __name__ == "__main__":
    sys.exit(main())
