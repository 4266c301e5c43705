"""The detector and transimpedance amplifier of the simulator's signal chain (``board_physics``): the TIA's first-order
low-pass of each channel (paper 3.5, Table 1), what the analogue TIA does to vibration above the sampled form, and the
output noise of paper Table 2 with the reference channel's read noise."""

from __future__ import annotations

import math

import numpy as np

from .lowpass import _first_order, _lowpass


class _TiaStages:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    the TIA low-pass, its vibration correction and the output noise."""

    def _tia_vibration_correction(self, t: np.ndarray, delay: float, u: np.ndarray, dT: np.ndarray,
                                  base: np.ndarray) -> np.ndarray:
        """What the analogue TIA does to the vibration sines beyond what its discrete form on the samples does (N, 3),
        axis-channel counts. The TIA (paper 3.5, Table 1) low-passes the photocurrent before the ADC samples it, so a
        sine above the Nyquist frequency reaches the counts at |H(f)| = 1/|1 + i 2 pi f tau| of its amplitude; filtering
        the samples instead aliases it first and passes it at the alias's gain (a 100.3 Hz vibration at 100 Hz came
        through like a 0.3 Hz one, 59x too strong on x). Per sine and axis channel j, in the small-signal response
        (``base`` (N, 3) x d resp / d u_j: counts per m/s^2 of axis input, the optics linearised at the sample's
        operating point ``u`` (N, 3), ``dT``): slope x Im((H_c - H_d) P e^(i w t)), H_c the analogue response, H_d the
        discrete filter's (``electronics.filter_discretisation``) to the sampled sine, P the sine's axis-input phasor
        (sensor frame, resonance, cross-axis coupling A, felt at t - delay like ``_axis_inputs``). Exact for the linear part;
        the optics' rectification (its mean) and harmonics stay as evaluated at the samples."""
        out = np.zeros((t.shape[0], 3))
        eps = 1e-3  # m/s^2: the response is smooth on this scale (pair separation changes by 1e-5 nm)
        slope = base * (self._optical_response(u + eps, dT) - self._optical_response(u - eps, dT)) / (2.0 * eps)
        tia_scale = self.cfg.scale("tia_lowpass")
        dt = self.dt_true
        for sine in self.sines:
            f = float(sine["freq_hz"])
            w = 2.0 * math.pi * f
            h_res = complex(self.resonance(f)) if self.resonance else 1.0
            amp = np.asarray(sine.get("amplitude_mps2", [0.0, 0.0, 0.0]), float).reshape(3)
            phasor = self.A @ (amp * h_res * np.exp(1j * math.radians(float(sine.get("phase_deg", 0.0)))))  # sensor frame
            zinv = np.exp(-1j * w * dt)
            for j in range(3):
                tau = tia_scale * self.tia_tau[j + 1]
                if tau <= 0.0:
                    continue
                a = math.exp(-dt / tau)
                if self.linear_filters:
                    r = tau / dt * -math.expm1(-dt / tau)
                    h_d = ((1.0 - r) + (r - a) * zinv) / (1.0 - a * zinv)
                else:
                    h_d = (1.0 - a) / (1.0 - a * zinv)
                h_c = 1.0 / (1.0 + 1j * w * tau)
                t_j = self._channel_time(t, delay, j)
                out[:, j] = slope[:, j] * np.imag((h_c - h_d) * phasor[j] * np.exp(1j * w * t_j))
        return out

    def _tia_lowpass(self, signal: np.ndarray) -> np.ndarray:
        """TIA first-order low-pass (N, 4) per channel, counts in and out (paper 3.5, Table 1; cut-offs in
        electronics.tia_cutoff_hz, time constants scaled by the tia_lowpass effect). Filter states stay on the object."""
        tia_scale = self.cfg.scale("tia_lowpass")
        if self._tia_state is None:
            self._tia_state, self._tia_xprev = signal[0].copy(), signal[0].copy()
        filtered = np.empty_like(signal)
        for j in range(4):
            tau = tia_scale * self.tia_tau[j]
            if self.linear_filters:  # exact for an input linear between samples (dynamic runs)
                filtered[:, j], self._tia_state[j], self._tia_xprev[j] = _lowpass(
                    signal[:, j], tau, self.dt_true, float(self._tia_state[j]), float(self._tia_xprev[j]), linear=True)
            else:
                alpha = math.exp(-self.dt_true / tau) if tau > 0 else 0.0
                filtered[:, j], st = _first_order(signal[:, j], alpha, self._tia_state[j:j + 1])
                self._tia_state[j] = st[0]
        return filtered

    def _output_noise(self, filtered: np.ndarray, rng_noise: np.random.Generator,
                      rng_ref: np.random.Generator) -> np.ndarray:
        """``filtered`` (N, 4 counts) with noise added in place: the axes' white (VRW) and bias-instability noise of paper
        Table 2, defined on the calibrated output (m/s^2) and injected through the small-signal slope (``rng_noise``:
        white, then bias instability), and the reference channel's ADC read noise (counts rms; ``rng_ref``)."""
        n = filtered.shape[0]
        n_a = self.white_scale * self._white_bank.step(rng_noise, n)
        bi = self._bi_bank.step(rng_noise, n).reshape(n, 3, -1).sum(axis=2)
        n_a = n_a + self.bi_scale * bi
        filtered[:, 1:] += (n_a @ self.A.T) * self.counts_per_mps2[None, :]
        if self.ref_noise > 0:
            filtered[:, 0] += rng_ref.standard_normal(n) * self.ref_noise
        return filtered
