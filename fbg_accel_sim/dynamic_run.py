"""A simulated dynamic-calibration run, through the wire: the board simulator runs an excitation plan
(slide + reference transducer on the aux channel, protocol version 2), its byte stream is decoded by
the driver's own ``StreamDecoder``, and the decoded frames become a ``Recording`` with ``aux`` -- what
``fbg-accel-calib dynamic`` reads from a bag or CSV (docs/dynamic_calibration.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fbg_accel_driver.stream_decoder import StreamDecoder

from .board_physics import BoardSimulator, SimBlock
from .sim_config import SimConfig


def simulate_dynamic_run(plan: Any, rate_hz: float = 500.0, seed: int = 0, overrides: dict[str, Any] | None = None,
                         tail_s: float = 2.0) -> tuple[Any, SimBlock, BoardSimulator]:
    """(Recording, truth block, simulator) of ``plan`` (an ``ExcitationPlan``) at the board rate ``rate_hz``.

    ``overrides``: further simulator-config keys (e.g. ``{"effects.channel_delay.scale": 0}``). The
    recording's ``t_s`` is the board clock (s), ``aux`` the decoded aux counts; frames lost or corrupted
    on the simulated link are simply absent, as for a real recording.
    """
    from fbg_accel_calibration.io.recording import Recording  # the simulator's existing dependency direction

    cfg = SimConfig.default().with_overrides({**plan.sim_overrides(), "scenario.rate_hz": float(rate_hz),
                                              **(overrides or {})})
    sim = BoardSimulator(cfg, seed=seed)
    n = sim.samples_for(plan.start_s + plan.duration_s + tail_s)
    block = sim.step(n)
    frames = StreamDecoder().feed(block.wire_bytes())
    if not frames:
        raise RuntimeError("the simulated run produced no decodable frame")
    arr = np.array([(f.t_us, f.ref, f.x, f.y, f.z, f.temp_cc, f.status, f.aux_counts) for f in frames], dtype=float)
    temp = arr[:, 5] / 100.0
    temp[(arr[:, 6].astype(int) & 1) == 0] = np.nan  # TEMP_VALID clear
    n_f = len(frames)
    rec = Recording(t_s=arr[:, 0] * 1e-6, ref=arr[:, 1], xyz=arr[:, 2:5], temp_c=temp,
                    gref_mps2=np.full((n_f, 3), np.nan), pose_id=np.full(n_f, -1), aux=arr[:, 7],
                    metadata={"source": "simulated dynamic run", "plan": plan.name, "rate_hz": rate_hz, "seed": seed})
    return rec, block, sim


def simulated_tone_check(plan: Any, cal: Any, rate_hz: float = 100.0, seed: int = 0,
                         overrides: dict[str, Any] | None = None,
                         modes: tuple[str, ...] = ("none", "delay", "equalise")) -> Any:
    """``dynamic_check.tone_check`` of ``cal`` on a simulated run of the one-tone ``plan``
    (``ExcitationPlan.with_tone``), over the tone's steady window; ``overrides`` as for :func:`simulate_dynamic_run`
    (the chain the run goes through)."""
    from fbg_accel_calibration.dynamic.dynamic_check import tone_check

    _, block, _ = simulate_dynamic_run(plan, rate_hz=rate_hz, seed=seed, overrides=overrides)
    _, a, b = plan.steady_windows(plan.start_s)[0]
    return tone_check(block.wire_bytes(), block.arrays["t_s"], block.arrays["slide_accel_mps2"],
                      np.array(plan.direction), plan.segments[0].freq_hz, (a, b), cal, modes=modes)


def random_channel_chain(seed: int, cutoff_range_hz: tuple[float, float] = (0.5, 5.0),
                         delay_range_s: tuple[float, float] = (0.0, 0.05)) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """A chain whose axis channels differ, as hand-built TIA stages with loose parts do: the x, y, z
    channels' TIA cut-offs (Hz) and pure delays (s) drawn uniformly from the ranges by ``default_rng(seed)``, and the
    simulator overrides that make it (reference channel at its configured cut-off; the common
    ``channel_delay.delay_s`` 0, each channel's delay in ``axis_channel_extra_s``). Returns (cut-offs, delays,
    overrides)."""
    rng = np.random.default_rng(seed)
    fc = rng.uniform(*cutoff_range_hz, 3)
    delay = rng.uniform(*delay_range_s, 3)
    ref_fc = float(SimConfig.default().get("electronics.tia_cutoff_hz")[0])
    return fc, delay, {"electronics.tia_cutoff_hz": [ref_fc, *(float(v) for v in fc)],
                       "effects.channel_delay.delay_s": 0.0,
                       "effects.channel_delay.axis_channel_extra_s": [float(v) for v in delay]}


def with_second_order_stage(rec: Any, rate_hz: float, f0_hz: float, q: float, channel: int = 1) -> Any:
    """A copy of ``rec`` with a second-order low-pass (natural frequency ``f0_hz`` [Hz], quality factor ``q``;
    bilinear transform at ``rate_hz`` [Hz], started at rest on the first sample) on one axis channel's counts
    (``channel`` 0/1/2 = x/y/z): a stage that the per-channel model (first-order low-pass + pure delay) does not
    represent, as an extra filter pole pair or a resonant mount would add. What the dynamic calibration's axis check
    must flag (docs/dynamic_calibration.md)."""
    from scipy import signal

    w0 = 2 * np.pi * f0_hz
    b, a = signal.bilinear([w0**2], [1.0, w0 / q, w0**2], fs=rate_hz)
    out = rec.select(np.ones(len(rec), dtype=bool))
    y = out.xyz[:, channel].copy()
    out.xyz[:, channel] = signal.lfilter(b, a, y, zi=signal.lfilter_zi(b, a) * y[0])[0]
    return out
