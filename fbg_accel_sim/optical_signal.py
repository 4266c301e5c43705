"""The optical signal of the simulator's signal chain (``board_physics``): the axis pairs' relative response through the
super-Gaussian spectral overlap (``optics``), and the light at the photodiodes in counts before the TIA -- source power
(tempco, wander, dropouts) times the chain gains (couplers, photodetectors, source wavelength drift, connector loss)."""

from __future__ import annotations

import numpy as np

from .optics import relative_response, source_factor


class _OpticalStages:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    the pairs' response and the source and chain gains."""

    def _optical_response(self, u: np.ndarray, dT: np.ndarray) -> np.ndarray:
        """Relative optical response (N, 3) of the axis pairs to the inputs ``u`` (m/s^2): pair separation
        d = d0 - S u (nm; S = 112 pm/g, paper eq. 21) + thermal mismatch (fbg_pair_thermal_mismatch, paper 4.4; ``dT``
        degC) through the super-Gaussian spectral overlap (paper eq. 13, 22; spectral_nonlinearity 0 = linearised)."""
        eff = self.cfg.get("effects")
        mm = eff["fbg_pair_thermal_mismatch"]
        d_extra = float(mm["scale"]) * dT[:, None] * np.asarray(mm["pm_per_c"], float)[None, :] * 1e-3
        return relative_response(u, self.d0, self.S, self.pair, float(eff["spectral_nonlinearity"]["scale"]), d_extra,
                                 self.rest_log_slope)

    def _source_and_gains(self, t: np.ndarray, dT: np.ndarray, resp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Optical signal (N, 4) in ADC counts before the TIA: rest counts x SLD power (tempco, paper 3.3, 3.6.2;
        slow wander drawn from ``rng``, the chunk's source stream; source_dropout windows) x chain gains (coupler and
        photodetector tempcos, SLD wavelength drift relative to the gratings: paper 3.6.2, 4.5; a connector's loss step,
        ASSUMPTION) x the axes' ``resp``."""
        eff = self.cfg.get("effects")
        n = t.shape[0]
        sp = eff["source_power_thermal"]
        p_src = 1.0 + float(sp["scale"]) * float(sp["tempco_per_c"]) * dT
        wander = self._wander_bank.step(rng, n)[:, 0] * float(eff["source_power_wander"]["scale"])
        p_src = p_src * (1.0 + wander)
        for wdw in self.windows["source_dropout"]:
            p_src = np.where(self._inside(t, wdw), p_src * float(wdw.get("level", 0.0)), p_src)
        gain = np.ones((n, 4))
        for name in ("coupler_thermal", "photodetector_thermal"):
            e = eff[name]
            gain *= 1.0 + float(e["scale"]) * dT[:, None] * np.asarray(e["tempco_per_c"], float)[None, :]
        cs = eff["connector_loss_step"]
        if float(cs["scale"]) != 0.0:  # a channel's loss steps once (connector knocked or re-mated; ASSUMPTION)
            after = (t >= float(cs["at_s"]))[:, None]
            loss = 10.0 ** (-0.1 * float(cs["scale"]) * np.asarray(cs["loss_db"], float))[None, :]
            gain *= np.where(after, loss, 1.0)
        sw = eff["source_wavelength_drift"]
        shift = float(sw["scale"]) * float(sw["drift_nm_per_c"]) * dT - self.fbg_thermal_nm * dT  # source minus gratings
        off = (self.pair_center - self.source_center)[None, :] - shift[:, None]
        gain[:, 1:] *= source_factor(off, self.sigma_g, self.sigma_s) / self.src0
        signal = self.rest_counts[None, :] * p_src[:, None] * gain
        signal[:, 1:] *= resp
        return signal
