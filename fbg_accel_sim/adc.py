"""The ESP32 ADC of the simulator's signal chain (``board_physics``): the channels it converts (:data:`CHANNELS` and the
aux channel's reference transducer), dark offsets, saturation windows, the codes' unequal widths and wide codes, the
clip to 0..adc_max and the 12-bit rounding."""

from __future__ import annotations

import numpy as np

from fbg_accel_driver.adc_code_table import pattern_codes

from .lowpass import _lowpass

CHANNELS = ("ref", "x", "y", "z")


class _AdcStages:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    the ADC's conversion of the four channels and of the aux channel."""

    def _codes(self, x: np.ndarray) -> np.ndarray:
        """ADC codes (int64, 0..adc_max) of counts ``x`` before the integer conversion."""
        return np.clip(np.round(x), 0, self.adc_max).astype(np.int64)

    def _adc(self, filtered: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Dark offsets (detector dark current + ESP32 ADC zero offset, counts; ASSUMPTION) and the ESP32 12-bit ADC
        (paper 3.5): adc_saturation windows force full scale, clip to 0..adc_max, round when adc_quantisation is on.
        Returns (counts before the integer conversion, codes), both (N, 4)."""
        do = self.cfg.get("effects.reference_dark_offset")
        counts_f = filtered + float(do["scale"]) * np.asarray(do["counts"], float)[None, :]
        for wdw in self.windows["adc_saturation"]:
            inside = self._inside(t, wdw)
            for chn in wdw.get("channels", ["x"]):
                counts_f[inside, CHANNELS.index(chn)] = float(self.adc_max)
        counts_f = self._wide_codes(self._code_widths(counts_f))
        return counts_f, self._codes(counts_f)

    def _code_widths(self, x: np.ndarray) -> np.ndarray:
        """``_adc_input`` of the four channels, with the codes' unequal widths when ``effects.adc_code_widths`` is on
        (and adc_quantisation): the ESP32's SAR ADC has differential non-linearity (Espressif, ESP32 datasheet, "ADC
        characteristics": DNL up to +-7 LSB, INL up to +-12 LSB); the measured series reads codes 16k 1.5-2.4x and
        16k + 8 3-6x less often than an even spread on every axis channel, a pattern periodic in the code
        (``fbg_accel_driver.adc_code_table.pattern_codes``). The widths are 1 + scale (w - 1) for the configured
        ``widths`` w (one period, summing to the period); one converter is multiplexed over the channels."""
        cw = self.cfg.get("effects.adc_code_widths")
        scale = float(cw["scale"])
        if scale == 0.0 or self.cfg.scale("adc_quantisation") == 0.0:
            return self._adc_input(x)
        w = 1.0 + scale * (np.asarray(cw["widths"], float) - 1.0)
        return pattern_codes(np.clip(x, 0.0, float(self.adc_max)), w, self.adc_max)

    def _adc_input(self, x: np.ndarray) -> np.ndarray:
        """Counts ``x`` clipped to the ADC range 0..adc_max and rounded when adc_quantisation is on."""
        x = np.clip(x, 0.0, float(self.adc_max))
        return np.round(x) if self.cfg.scale("adc_quantisation") != 0.0 else x

    def _wide_codes(self, counts_f: np.ndarray) -> np.ndarray:
        """Wide codes of the ESP32's SAR ADC (differential non-linearity; one value read over a range of input voltages:
        esp32.com forum, "Strange ADC Measurements", viewtopic.php?t=18674; the measured series reads y = 1535 through
        five whole visits while the codes 1536-1543 never occur). Each ``[code, width]`` of ``effects.adc_wide_codes``
        reads every input from code - 0.5 to code + width - 0.5 counts as ``code`` (the next width - 1 codes are
        missing), on every channel: one converter is multiplexed over them. Off unless the scale is non-zero."""
        wide = self.cfg.get("effects.adc_wide_codes")
        if float(wide["scale"]) == 0.0 or not wide["codes"]:
            return counts_f
        out = counts_f.copy()
        for code, width in wide["codes"]:
            out[(counts_f >= code - 0.5) & (counts_f < code + width - 0.5)] = float(code)
        return out

    def _aux_counts(self, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Aux channel (N,) counts before rounding: the reference transducer measuring the true slide motion,
        converted 4 skews after t_us (after ref, x, y, z), clipped to the ADC range (rounded if quantised)."""
        n = t.shape[0]
        rc = self.ref_cfg
        if self.ref_type == "none":
            return np.zeros(n)
        if self.slide is not None:
            _, vel, acc = self.slide.kinematics(t + 4.0 * self.skew_s)
        else:
            vel = acc = np.zeros(n)
        if self.ref_type == "ldv":  # velocity output (seed 2, 2.1), AC coupling of the input (seed 2, Fig. 5)
            sig = vel
            if self.ldv_hp_tau > 0.0:
                if self._aux_lp is None:
                    self._aux_lp = (float(sig[0]), float(sig[0]))
                lp, ylast, xlast = _lowpass(sig, self.ldv_hp_tau, self.dt_true, *self._aux_lp, linear=self.linear_filters)
                self._aux_lp = (ylast, xlast)
                sig = sig - lp  # first-order high-pass = input - low-pass
            out = float(rc["ldv"]["offset_counts"]) + float(rc["ldv"]["sensitivity_counts_per_mps"]) * sig
        else:  # reference accelerometer, DC coupled
            out = (float(rc["accelerometer"]["offset_counts"])
                   + float(rc["accelerometer"]["sensitivity_counts_per_mps2"]) * acc)
        noise = float(rc["noise_counts"])
        if noise > 0:
            out = out + rng.standard_normal(n) * noise
        return self._adc_input(out)
