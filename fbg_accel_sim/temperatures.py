"""The temperatures of the simulator's signal chain (``board_physics``): chamber -> optics (thermal inertia) -> AHT10 die
(thermal lag), the AHT10 reading (sample-and-hold, offset, noise, resolution) with its unflagged faults, and the frames'
temperature word with its TEMP_PRESENT / TEMP_VALID flags."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .lowpass import _first_order


class _Temperatures(NamedTuple):
    """Chamber, optics and AHT10 die temperatures (degC) and the optics' offset from the reference temperature."""

    chamber_c: np.ndarray
    optics_c: np.ndarray
    sensor_c: np.ndarray
    delta_ref_c: np.ndarray  # optics - thermal.reference_temperature_c


class _TemperatureWord(NamedTuple):
    """Temperature field of the frames: temp_cc (0.01 degC) and the TEMP_PRESENT / TEMP_VALID flags."""

    temp_cc: np.ndarray
    present: np.ndarray
    valid: np.ndarray


class _TemperatureStages:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    the optics' and the AHT10's temperatures and what the frames carry of them."""

    def _temperatures(self, t: np.ndarray) -> _Temperatures:
        """Chamber profile -> optics (first-order thermal inertia, paper 4.4: tau ~ 5000 s) -> AHT10 die (thermal_lag
        effect, paper 3.5; tau ASSUMPTION), degC at ``t`` (s); ``delta_ref_c`` = optics - reference temperature (paper 4.3).
        The optics and die filter states carry from chunk to chunk on the object."""
        c = self.cfg
        T_ch = self.chamber(t)
        a_opt = math.exp(-self.dt_true / float(c.get("thermal.optics_time_constant_s")))
        housing, self._T_housing = _first_order(T_ch, a_opt, self._T_housing)
        thermal_lag = c.get("effects.thermal_lag")
        lag = float(thermal_lag["scale"]) * float(thermal_lag["time_constant_s"])
        a_lag = math.exp(-self.dt_true / lag) if lag > 0 else 0.0
        inner, self._T_inner = _first_order(housing, a_lag, self._T_inner)
        # the AHT10 die lags the optics (it sits on the PCB behind them), or with reading_leads the optics lag the die
        # (the die nearer the chamber air than the optics bonded inside the housing)
        T_opt, T_sen = (inner, housing) if thermal_lag.get("reading_leads", False) else (housing, inner)
        return _Temperatures(T_ch, T_opt, T_sen, T_opt - self.T_ref)

    def _aht10_reading(self, t: np.ndarray, T_sen: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """AHT10 reading (degC) of the die temperature ``T_sen``: sample-and-hold at aht10.read_rate_hz (ASSUMPTION),
        per-device offset (accuracy +-0.3 degC, paper 3.5) + noise (AHT10 datasheet repeatability; drawn from ``rng``)
        and 0.01 degC resolution (paper 3.5, AHT10 datasheet) when aht10_error is on. The hold stays on the object."""
        aht = self.cfg.get("aht10")
        ae = self.cfg.scale("aht10_error")
        n = t.shape[0]
        r_idx = np.floor(t * float(aht["read_rate_hz"])).astype(np.int64)
        noise_aht = rng.standard_normal(n) * float(aht["noise_c"]) * ae
        raw = T_sen + ae * self.aht_offset + noise_aht
        prev_idx = np.concatenate([[self._aht_last[0]], r_idx[:-1]])
        change = r_idx != prev_idx
        pos = np.where(change, np.arange(n), -1)
        held_pos = np.maximum.accumulate(pos)
        reading = np.where(held_pos >= 0, raw[np.maximum(held_pos, 0)], self._aht_last[1])
        self._aht_last = (int(r_idx[-1]), float(reading[-1]))
        if ae > 0:
            res = float(aht["resolution_c"])
            reading = np.round(reading / res) * res
        return reading

    def _reading_faults(self, t: np.ndarray, reading: np.ndarray) -> np.ndarray:
        """The AHT10 reading (degC) as the firmware delivers it, with the unflagged faults of
        ``faults.temperature_reading`` (config/sim_default.yaml cites each): a step from ``at_s`` on (sensor re-seated),
        one read off by ``size_c`` (a bit of the 20-bit word flipped; AHT10 datasheet T = S_T / 2^20 x 200 - 50 degC) and
        a frozen stretch repeating the last delivered value (a conversion that never completes read again). No random
        draw: without a fault the reading is returned unchanged."""
        spec = self.reading_faults
        if not (spec.get("steps") or spec.get("frozen") or (spec.get("spikes") or {}).get("at_s")):
            return reading  # none configured (the default): no copy and no masks on every chunk
        out = reading.copy()
        for st in spec.get("steps") or []:
            out[t >= float(st["at_s"])] += float(st["step_c"])
        sp = spec.get("spikes") or {}
        rate = float(self.cfg.get("aht10")["read_rate_hz"])
        for at in sp.get("at_s") or []:
            out[np.floor(t * rate) == math.floor(float(at) * rate)] += float(sp["size_c"])
        frozen = np.zeros(len(t), bool)
        for wdw in spec.get("frozen") or []:
            frozen |= self._inside(t, wdw)
        if frozen.any():
            last = np.maximum.accumulate(np.where(~frozen, np.arange(len(t)), -1))
            held = self._delivered_last if self._delivered_last is not None else float(out[0])
            out = np.where(frozen, np.where(last >= 0, out[np.maximum(last, 0)], held), out)
        self._delivered_last = float(out[-1])
        return out

    def _temperature_word(self, t: np.ndarray, reading: np.ndarray) -> _TemperatureWord:
        """Temperature field of the frames (docs/protocol.md): ``reading`` (degC) in 0.01 degC, TEMP_PRESENT and
        TEMP_VALID per sample (faults temperature_absent, temperature_invalid). Invalid: the firmware keeps sending the
        last valid value (kept on the object across chunks); absent: 0."""
        n = t.shape[0]
        temp_cc = np.round(reading * 100.0).astype(np.int64)
        present = np.full(n, not self.temp_absent_from_boot)
        valid = present.copy()
        for wdw in self.windows["temperature_absent"]:
            present &= ~self._inside(t, wdw)
        valid &= present
        for wdw in self.windows["temperature_invalid"]:
            valid &= ~self._inside(t, wdw)
        vpos = np.maximum.accumulate(np.where(valid, np.arange(n), -1))
        held_cc = np.where(vpos >= 0, temp_cc[np.maximum(vpos, 0)], self._last_valid_cc)
        if valid.any():
            self._last_valid_cc = int(temp_cc[np.flatnonzero(valid)[-1]])
        return _TemperatureWord(np.where(valid, temp_cc, np.where(present, held_cc, 0)), present, valid)
