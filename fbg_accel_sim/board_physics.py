"""Physics-based simulator of the FBG accelerometer's acquisition board (pure numpy, no ROS).

Batch API (contract in the team brief)::

    cfg = SimConfig.load("config/sim_default.yaml").with_overrides({"scenario.rate_hz": 100.0})
    sim = BoardSimulator(cfg, seed=0)
    block = sim.step(n)          # next n board samples: truth arrays + frames() + wire_bytes()
    rec = simulate_recording(cfg, seed=0, duration_s=60.0)   # -> Recording

Signal chain per sample (docs/simulator.md has the equations and the source of each effect):

    table angles (t - delay) -> specific force f (table frame) -> mount rotation + vibration + slide
       (dynamic inputs through the mechanical resonance; channel j evaluated j x ADC skew later)
    -> axis inputs u = A f + equivalent biases (time drift, hysteresis, cable torque, motion hysteresis)
    -> FBG pair separation d = d0 - S u + thermal mismatch -> super-Gaussian spectral overlap (eq. 13)
    -> optical power x source power (temperature, wander, dropout) x chain gains (SLD wavelength
       drift, couplers, photodiodes) -> counts at rest scale -> TIA first-order low-pass
    -> + noise (Table 2) + dark offsets -> 12-bit ADC (round, clip 0..4095)
    AHT10: chamber -> optics (thermal inertia) -> sensor (thermal lag) -> offset, noise, 0.01 degC
    aux (protocol v2): true slide velocity (LDV, AC-coupled) or acceleration -> counts -> 12-bit ADC

Everything random is drawn per fixed-size generation chunk from ``(seed, chunk, stream)``, so the
output depends only on the seed and the config, never on how ``step`` calls are sized.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from fbg_accel_driver.frame_codec import BODY_LEN_BY_VERSION, Frame, crc16, frame_size

from . import faults as fz
from .adc import CHANNELS, _AdcStages
from .board_framing import _BoardFraming
from .detector_tia import _TiaStages
from .mechanics import _MechanicsStages
from .noise import GaussMarkovBank, NoiseModel
from .optical_signal import _OpticalStages
from .optics import STANDARD_G, PairOverlap, grating_sigma_nm, source_factor
from .scenario import TemperatureProfile, build_slide, build_trajectory, second_order_response
from .sim_config import SimConfig
from .temperatures import _TemperatureStages

CHUNK = 2048  # samples per generation chunk (fixed: determinism does not depend on step sizes)
_COUNT_COLUMNS: dict[str, int | slice] = {**{c: j for j, c in enumerate(CHANNELS)}, "xyz": slice(1, None)}
_STREAM_NOISE, _STREAM_SOURCE, _STREAM_AHT, _STREAM_WIRE, _STREAM_REFNOISE, _STREAM_AUX = 1, 2, 3, 4, 5, 6

__all__ = ["CHUNK", "BoardSimulator", "SimBlock", "SimConfig", "simulate_recording"]


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m = np.eye(3)
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    if axis == 1:
        m[i, j], m[j, i] = s, -s
    return m


class _WireFaults(NamedTuple):
    """Wire faults of a chunk: per-sample arrays and, by index in the chunk, the random details of each fault."""

    code: np.ndarray  # fz.DROP, ... (0 = none)
    garbage_before: np.ndarray  # bytes of garbage before the sample's frame
    trunc_len_per_sample: np.ndarray  # nominal truncation length (bytes; the wire guards may shorten it)
    flip_bit: dict[int, int]
    trunc_len: dict[int, int]
    garbage: dict[int, bytes]


@dataclass
class _Chunk:
    """Everything generated for one chunk of CHUNK samples (arrays of length CHUNK)."""

    arrays: dict[str, np.ndarray]
    faults: _WireFaults  # the random details of its wire faults, by index in the chunk
    pieces: list[bytes] | None = None  # wire bytes per sample (lazy)


@dataclass
class SimBlock:
    """``n`` consecutive board samples: truth arrays (N,) / (N, k), fault log, frames and bytes."""

    arrays: dict[str, np.ndarray]
    counters: dict[str, int]
    _pieces: list[bytes] | None = field(repr=False, default_factory=list)
    protocol_version: int = 1  # of the frames: 2 carries the aux counts

    def __getattr__(self, name: str) -> Any:
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        if name in _COUNT_COLUMNS:  # ref, x, y, z, xyz: columns of the counts (N, 4)
            return arrays["counts"][:, _COUNT_COLUMNS[name]]
        counters = self.__dict__.get("counters", {})
        if name in counters:
            return counters[name]
        raise AttributeError(name)

    def __len__(self) -> int:
        return int(self.arrays["t_s"].shape[0])

    def wire_bytes(self) -> bytes:
        """The byte stream the board puts on the link for these samples, faults included."""
        return b"".join(self._wire())

    def wire_pieces(self) -> list[bytes]:
        """Bytes on the wire per sample (garbage burst before it + its frame as sent; b"" if unsent)."""
        return list(self._wire())

    def _wire(self) -> list[bytes]:
        if self._pieces is None:
            raise RuntimeError("this simulator was created with wire=False: no byte stream")
        return self._pieces

    def frames(self) -> list[Frame]:
        """Frames that arrive intact, in wire order (a duplicated frame appears twice; dropped,
        bit-flipped and truncated frames are absent)."""
        a = self.arrays
        out: list[Frame] = []
        deliver = a["sent"] & ~np.isin(a["wire_fault"], (fz.DROP, fz.BIT_FLIP, fz.TRUNCATE))
        v2 = self.protocol_version == 2
        for i in np.flatnonzero(deliver):
            f = Frame(int(a["seq"][i]), int(a["t_us"][i]), *(int(v) for v in a["counts"][i]), int(a["temp_cc"][i]),
                      int(a["status"][i]), int(a["aux"][i]) if v2 else None)
            out.append(f)
            if a["wire_fault"][i] == fz.DUPLICATE:
                out.append(f)
        return out


class BoardSimulator(_MechanicsStages, _TemperatureStages, _OpticalStages, _TiaStages, _AdcStages, _BoardFraming):
    """Streaming simulator of the board: ``step(n) -> SimBlock`` (deterministic for a seed).

    The stages of the signal chain are methods of the classes it is made of, one module per job: ``mechanics``,
    ``temperatures``, ``optical_signal``, ``detector_tia``, ``adc``, ``board_framing``; here the set-up, the public
    API, the generation of a chunk through those stages in order, the wire bytes and the counters."""

    def __init__(self, cfg: SimConfig | None = None, seed: int = 0, wire: bool = True) -> None:
        """``wire=False`` skips building the byte stream (faster batch runs; ``expected_bytes_discarded``
        then uses the nominal truncation lengths, which the wire guards may shorten)."""
        self.wire = wire
        self.cfg = cfg if cfg is not None else SimConfig.default()
        self.seed = int(seed)
        c = self.cfg
        sc = c.get("scenario")
        self.rate_hz = float(sc["rate_hz"])
        if not (self.rate_hz > 0):
            raise ValueError("scenario.rate_hz must be > 0")
        self.clock_ppm = float(c.get("board.clock_ppm"))
        # The board clock runs (1 + ppm) fast: it takes rate_hz (1 + ppm 1e-6) samples per true second.
        self.rate_true_hz = self.rate_hz * (1.0 + self.clock_ppm * 1e-6)
        self.dt_true = 1.0 / self.rate_true_hz
        self.trajectory = build_trajectory(sc["poses"])
        self.chamber = TemperatureProfile(float(sc["temperature"]["initial_c"]), sc["temperature"]["profile"])
        self.gravity = float(sc["gravity_mps2"])
        self.sines = sc["vibration"]["sines"]
        self.slide = build_slide(sc["slide"])
        dur = sc.get("duration_s")
        self.duration_s = float(dur) if dur is not None else self.trajectory.duration_s
        if dur is None and self.slide is not None and not math.isfinite(self.duration_s):
            # A static table with a slide plan ends after the plan plus as much rest as before it.
            self.duration_s = self.slide.end_s + float(self.slide.starts[0])
        self._setup_dynamics()
        self._setup_optics()
        self._setup_noise()
        self._setup_board_and_faults()
        self._setup_state()
        self.sample_index = 0
        self._chunks: dict[int, _Chunk] = {}
        self.totals: dict[str, int] = {}
        self._expected = fz.ExpectedDecoder()

    # ------------------------------------------------------------------ setup
    def _setup_dynamics(self) -> None:
        """Protocol version, ADC channel skew, filter discretisation, resonance, reference transducer."""
        c = self.cfg
        self.protocol_version = int(c.get("board.protocol_version"))
        if self.protocol_version not in BODY_LEN_BY_VERSION:
            raise ValueError(f"board.protocol_version {self.protocol_version} unknown (1 or 2)")
        self.frame_size = frame_size(self.protocol_version)
        self.skew_s = float(c.get("board.adc_channel_skew_us")) * 1e-6
        if not (self.skew_s >= 0 and self.skew_s * 4 < 1.0 / self.rate_hz):
            raise ValueError("board.adc_channel_skew_us must be >= 0 and 4 skews must fit in one sample period")
        extra = np.asarray(c.get("effects.channel_delay.axis_channel_extra_s"), float).reshape(-1)
        if extra.shape != (3,) or not np.all(np.isfinite(extra) & (extra >= 0)):
            raise ValueError("effects.channel_delay.axis_channel_extra_s must be 3 delays >= 0 (s) for x, y, z")
        # per axis channel: its own delay on top of the common one (both scaled by the effect's scale)
        self.channel_extra_delay_s = c.scale("channel_delay") * extra
        disc = str(c.get("electronics.filter_discretisation"))
        if disc not in ("auto", "hold", "linear"):
            raise ValueError(f"electronics.filter_discretisation '{disc}' unknown (auto, hold, linear)")
        self.linear_filters = disc == "linear" or (disc == "auto" and self.slide is not None)
        res = c.get("effects.mechanical_resonance")
        r_scale, fn, zeta = float(res["scale"]), float(res["natural_freq_hz"]), float(res["damping_ratio"])
        if r_scale != 0.0 and not (fn > 0 and zeta > 0):
            raise ValueError("effects.mechanical_resonance: natural_freq_hz and damping_ratio must be > 0")
        self.resonance = (None if r_scale == 0.0 else
                          (lambda f: 1.0 + r_scale * (second_order_response(f, fn, zeta) - 1.0)))
        ref = c.get("reference_transducer")
        self.ref_type = str(ref["type"])
        if self.ref_type not in ("ldv", "accelerometer", "none"):
            raise ValueError(f"reference_transducer.type '{self.ref_type}' unknown (ldv, accelerometer, none)")
        self.ref_cfg = ref
        hp = ref["ldv"].get("ac_coupling_hz")
        self.ldv_hp_tau = 1.0 / (2.0 * math.pi * float(hp)) if hp else 0.0
        self._aux_lp: tuple[float, float] | None = None  # LDV AC-coupling state: (low-pass y, last input)
        self._tia_xprev: np.ndarray | None = None  # last TIA input per channel (linear discretisation)

    def _setup_optics(self) -> None:
        c = self.cfg
        o = c.get("optics")
        rc = o["rest_counts"]
        # rest_counts are what the ADC shows at rest with the nominal dark offsets; the optical signal part
        # excludes them, so switching reference_dark_offset off removes the offset and keeps the signal.
        nominal_dark = np.asarray(c.get("effects.reference_dark_offset.counts"), float)
        self.rest_counts = np.array([float(rc[k]) for k in CHANNELS]) - nominal_dark
        self.d0 = float(o["pair_separation_nm"])
        self.S = float(o["differential_sensitivity_pm_per_g"]) * 1e-3 / STANDARD_G  # nm per m/s^2
        self.sigma_g = grating_sigma_nm(np.asarray(o["grating_fwhm_nm"], float))  # equivalent Gaussian (source factor)
        self.pair = PairOverlap(o["grating_fwhm_nm"], o["grating_super_gaussian_order"])
        self.pair_center = np.asarray(o["pair_center_nm"], float)
        self.fbg_thermal_nm = float(o["fbg_thermal_pm_per_c"]) * 1e-3
        self.sigma_s = float(c.get("source.fwhm_nm")) / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        self.source_center = float(c.get("source.center_nm"))
        if o.get("cross_axis_from_published_M", True):
            J = np.linalg.inv(np.asarray(o["published_M"], float))
            self.A = J / np.diag(J)[:, None]
        else:
            self.A = np.eye(3)
        r, p, y = (float(v) for v in o["mount_rpy_deg"])
        self.R_mount = (_rot(2, y) @ _rot(1, p) @ _rot(0, r)).T  # f_sensor = R_mount f_table
        self.T_ref = float(c.get("thermal.reference_temperature_c"))
        # Small-signal slope of the axis counts per m/s^2 of axis input at rest (linearised overlap).
        self.rest_log_slope = self.pair.log_derivatives(self.d0)[0]  # O'/O at d0, 1/nm (negative)
        self.rel_slope = -self.rest_log_slope * self.S  # 1/(m/s^2)
        self.counts_per_mps2 = self.rest_counts[1:] * self.rel_slope
        self.src0 = source_factor(self.pair_center - self.source_center, self.sigma_g, self.sigma_s)
        fc = np.asarray(c.get("electronics.tia_cutoff_hz"), float)
        self.tia_tau = 1.0 / (2.0 * math.pi * fc)
        self.adc_max = int(c.get("electronics.adc_max_counts"))

    def _setup_noise(self) -> None:
        n = self.cfg.get("noise")
        fc = np.asarray(self.cfg.get("electronics.tia_cutoff_hz"), float)[1:]
        self.noise_model = NoiseModel(n["vrw_mps_per_sqrt_h"], n["bias_instability_mg"], fc,
                                      n["bias_instability_time_constants_s"], self.rate_hz)
        self.white_scale = self.cfg.scale("white_noise")
        self.bi_scale = self.cfg.scale("bias_instability")
        self.ref_noise = float(n["reference_noise_counts"])

    def _setup_board_and_faults(self) -> None:
        c = self.cfg
        f = c.get("faults")
        self.fcfg = f
        gap_n = max(1, round(float(c.get("board.boot_gap_s")) * self.rate_true_hz))
        resets = sorted(float(t) for t in (f["resets"].get("at_s") or []))
        self.reset_k = np.array([math.ceil(t * self.rate_true_hz - 1e-9) for t in resets], dtype=np.int64)
        self.epoch_start = np.concatenate([[0], self.reset_k + gap_n]).astype(np.int64)
        self.gap_n = gap_n
        dspec = f["disconnects"]
        self.disconnects = [(float(t), float(dspec.get("down_s", 1.0))) for t in (dspec.get("at_s") or [])]
        self.disconnect_removes_link = bool(dspec.get("remove_link", False))
        self._disc_k = [(math.ceil(t * self.rate_true_hz - 1e-9), math.ceil((t + d) * self.rate_true_hz - 1e-9))
                        for t, d in self.disconnects]
        # BOOT marks the first frame the board's writer SENDS after a (re)boot, not the first sample: the writer
        # discards frames while its link is down (Bluetooth SPP with no client, writer_task in
        # firmware/esp32/fbg_board/fbg_board.ino) and puts BOOT on the first frame it sends (fbg_link_on_send,
        # firmware/core/fbg_board.c). A disconnect window over an epoch's start moves BOOT to the first sample after
        # it (seq no longer 0); an epoch with no sent sample has none (-1).
        ends = np.concatenate([self.reset_k, [np.iinfo(np.int64).max]])
        self.boot_k = np.array([self._first_sent_k(int(s0), int(e0)) for s0, e0 in zip(self.epoch_start, ends, strict=True)],
                               dtype=np.int64)
        end = f.get("end_s")
        end_s = float(end) if end is not None else self.duration_s
        rng = np.random.default_rng([self.seed, 0, _STREAM_WIRE])
        self.schedule = fz.schedule_faults(f, self.rate_true_hz, end_s, rng, lambda k: bool(self._unsent(k)), CHUNK)
        self._wire_k = np.array(sorted(self.schedule.wire), dtype=np.int64)
        self._garbage_k = np.array(sorted(self.schedule.garbage), dtype=np.int64)
        self.windows = {name: list(f[name].get("windows") or []) for name in
                        ("adc_saturation", "source_dropout", "temperature_invalid", "temperature_absent", "adc_overrun")}
        self.temp_absent_from_boot = bool(f["temperature_absent"].get("from_boot", False))
        self.reading_faults = f["temperature_reading"]
        self._setup_late_reads(f["late_reads"])

    def _setup_state(self) -> None:
        c = self.cfg
        rng = np.random.default_rng([self.seed, 0, 0])
        aht = c.get("aht10")
        off = aht.get("offset_c")
        acc = float(aht["accuracy_c"])
        self.aht_offset = float(off) if off is not None else float(rng.uniform(-acc, acc))
        t_init = c.get("thermal.initial_optics_c")
        t0 = float(self.chamber(np.array([0.0]))[0])
        self._T_housing = np.array([float(t_init) if t_init is not None else t0])  # first stage: the housing
        self._T_inner = self._T_housing.copy()  # second stage: the part that lags it (thermal_lag)
        self._play = float(self._T_housing[0])
        self._force_play: np.ndarray | None = None  # play operator of each axis' specific force (motion_hysteresis)
        self._tia_state: np.ndarray | None = None
        nm = self.noise_model
        self._white_bank = GaussMarkovBank([ax.white_q for ax in nm.axes], [ax.white_rho for ax in nm.axes], rng)
        self._bi_bank = GaussMarkovBank(np.concatenate([ax.bi_q for ax in nm.axes]),
                                        np.concatenate([ax.bi_rho for ax in nm.axes]), rng)
        w = c.get("effects.source_power_wander")
        self._wander_bank = GaussMarkovBank([float(w["relative_sigma"]) ** 2],
                                            [math.exp(-self.dt_true / float(w["time_constant_s"]))], rng)
        self._aht_last = (-1, 0.0)  # (read index, value degC)
        self._last_valid_cc = 0
        self._delivered_last: float | None = None  # last AHT10 reading the firmware delivered (faults.temperature_reading)

    # ------------------------------------------------------------------ public API
    @property
    def t_s(self) -> float:
        """True time (s) of the next sample."""
        return self.sample_index * self.dt_true

    def samples_for(self, duration_s: float) -> int:
        return math.floor(duration_s * self.rate_true_hz + 1e-9)

    def step(self, n: int, deliver: bool = True) -> SimBlock:
        """The next ``n`` samples. ``deliver=False``: the link is down for them (nothing is sent; the
        samples count as ``unsent_frames`` and the expected decoder counts them as lost)."""
        if n < 0:
            raise ValueError("n must be >= 0")
        parts: dict[str, list[np.ndarray]] = {}
        pieces: list[bytes] | None = [] if self.wire else None
        for ci, ch, a, b in self._spans(n):
            for key, arr in ch.arrays.items():
                parts.setdefault(key, []).append(arr[a:b])
            if pieces is not None:
                pieces.extend(self._wire_pieces(ch, ci)[a:b])
        arrays = {k: np.concatenate(v) for k, v in parts.items()} if n else self._empty_arrays()
        if not deliver:
            arrays["sent"] = np.zeros(n, bool)
            pieces = [b""] * n if pieces is not None else None
        return SimBlock(arrays, self._count(arrays), pieces, self.protocol_version)

    def step_bytes(self, n: int) -> bytes:
        """Wire bytes of the next ``n`` samples only (fast path of the pty server; the truth counters
        ``totals`` and ``expected_decoder_stats`` are not updated by this call)."""
        return b"".join(p for ci, ch, a, b in self._spans(n) for p in self._wire_pieces(ch, ci)[a:b])

    def _spans(self, n: int) -> Iterator[tuple[int, _Chunk, int, int]]:
        """The chunks of the next ``n`` samples as (chunk index, chunk, first, end) within the chunk; afterwards the
        samples are consumed and chunks used up are dropped."""
        k0, k1 = self.sample_index, self.sample_index + n
        for ci in range(k0 // CHUNK, (k1 - 1) // CHUNK + 1 if n else k0 // CHUNK):
            ch = self._get_chunk(ci)
            b = min(k1, (ci + 1) * CHUNK) - ci * CHUNK
            yield ci, ch, max(k0, ci * CHUNK) - ci * CHUNK, b
            if b == CHUNK:
                self._chunks.pop(ci, None)
        self.sample_index = k1

    def run(self, duration_s: float, block: int = 65536) -> SimBlock:
        """Concatenated blocks for ``duration_s`` of true time from the current sample (truth only;
        ``wire_bytes``/``frames`` of the result cover the whole span)."""
        n_total = self.samples_for(duration_s)
        blocks = [self.step(min(block, n_total - k)) for k in range(0, n_total, block)] or [self.step(0)]
        arrays = {k: np.concatenate([b.arrays[k] for b in blocks]) for k in blocks[0].arrays}
        counters = {k: sum(b.counters[k] for b in blocks) if not k.startswith("total_") else blocks[-1].counters[k]
                    for k in blocks[0].counters}
        pieces = [p for b in blocks for p in b._pieces] if self.wire else None
        return SimBlock(arrays, counters, pieces, self.protocol_version)

    def expected_decoder_stats(self) -> dict[str, int]:
        """What a ``StreamDecoder`` fed all bytes so far from the first one must report."""
        e = self._expected
        t = self.totals
        return {"frames": e.frames, "crc_errors": t.get("injected_crc_errors", 0), "lost_frames": e.lost_frames,
                "duplicates": e.duplicates, "resets": e.resets, "bytes_discarded": t.get("expected_bytes_discarded", 0),
                "invalid_frames": 0, "unsupported_version": 0}

    def configured_noise(self) -> dict[str, Any]:
        """Noise targets and the model a test of the Allan tool compares with (m/s^2, s)."""
        nm = self.noise_model
        return {"vrw_mps_per_sqrt_h": nm.vrw * self.white_scale, "bias_instability_mg": nm.bi_mg * self.bi_scale,
                "adev_1s_mps2": nm.expected_adev([1.0], self.white_scale, self.bi_scale)[0],
                "min_adev_mps2": nm.target_min_adev, "min_adev_tau_s": nm.min_adev_tau_s,
                "sample_sigma_mps2": nm.sample_sigma(self.white_scale, self.bi_scale), "model": nm}

    # ------------------------------------------------------------------ generation
    def _empty_arrays(self) -> dict[str, np.ndarray]:
        ch = self._get_chunk(self.sample_index // CHUNK)
        return {k: v[:0] for k, v in ch.arrays.items()}

    def _get_chunk(self, ci: int) -> _Chunk:
        if ci not in self._chunks:
            nxt = self._generated_upto + 1
            while nxt <= ci:  # generate sequentially (state carries from chunk to chunk)
                self._chunks[nxt] = self._generate(nxt)
                nxt += 1
        return self._chunks[ci]

    _generated_upto = -1

    def _rng(self, ci: int, stream: int) -> np.random.Generator:
        """Random stream ``stream`` of chunk ``ci`` (chunk index 0 of the seed holds the set-up draws)."""
        return np.random.default_rng([self.seed, ci + 1, stream])

    @staticmethod
    def _inside(t: np.ndarray, wdw: dict[str, Any]) -> np.ndarray:
        """Samples at ``t`` (s) inside the fault window ``{start_s, duration_s}`` (start included, end excluded)."""
        return (t >= float(wdw["start_s"])) & (t < float(wdw["start_s"]) + float(wdw["duration_s"]))

    def _generate(self, ci: int) -> _Chunk:
        """Chunk ``ci`` through the signal chain of the module docstring, one stage per physical effect. Each random
        stream ``(seed, chunk, stream)`` feeds a single stage, which draws from it in a fixed order."""
        if ci != self._generated_upto + 1:
            raise RuntimeError("chunks must be generated in order")
        self._generated_upto = ci
        k = np.arange(ci * CHUNK, (ci + 1) * CHUNK, dtype=np.int64)
        # a late read (faults.late_reads) samples the inputs when it is taken; the discrete filters still step one period
        late = self._late_offsets(k)
        t = k * self.dt_true + late * (self.rate_hz * self.dt_true)  # board s -> true s
        delay = self.cfg.scale("channel_delay") * float(self.cfg.get("effects.channel_delay.delay_s"))
        table = self._table_motion(t, delay)
        slide, table = self._linear_slide(t, delay, table)
        temps = self._temperatures(t)
        bias = self._axis_biases(t, temps.optics_c, table.psi_felt_deg, table.felt_mps2)
        u = self._axis_inputs(t, delay, table.felt_mps2, bias)
        resp = self._optical_response(u, temps.delta_ref_c)
        signal = self._source_and_gains(t, temps.delta_ref_c, resp, self._rng(ci, _STREAM_SOURCE))
        filtered = self._tia_lowpass(signal)
        if self.sines:  # the analogue TIA on vibration above what its discrete form does (no sines: nothing to add)
            filtered[:, 1:] += self._tia_vibration_correction(t, delay, u, temps.delta_ref_c, signal[:, 1:] / resp)
        filtered = self._output_noise(filtered, self._rng(ci, _STREAM_NOISE), self._rng(ci, _STREAM_REFNOISE))
        counts_f, counts = self._adc(filtered, t)
        aux_f = self._aux_counts(t, self._rng(ci, _STREAM_AUX))
        reading = self._reading_faults(t, self._aht10_reading(t, temps.sensor_c, self._rng(ci, _STREAM_AHT)))
        word = self._temperature_word(t, reading)
        board = self._board_framing(k, t, word.present, word.valid, late)
        wire = self._wire_faults(ci, self._rng(ci, _STREAM_WIRE))
        arrays = {
            "t_s": t, "board_t_s": board.board_t_s, "pose_id": table.pose_id.astype(np.int64), "in_motion": table.in_motion,
            "visit": table.visit.astype(np.int64), "time_at_pose_s": table.time_at_pose_s,
            "psi_deg": table.psi_deg, "theta_deg": table.theta_deg, "accel_true_mps2": table.accel_true_mps2,
            "gref_mps2": table.gref_mps2,
            "temp_chamber_c": temps.chamber_c, "temp_optics_c": temps.optics_c, "temp_sensor_true_c": temps.sensor_c,
            "temp_sensor_c": reading, "temp_valid": word.valid, "temp_present": word.present,
            "counts": counts, "counts_float": counts_f, "saturated": counts >= self.adc_max,
            "seq": board.seq.astype(np.int64), "t_us": board.t_us, "status": board.status, "temp_cc": word.temp_cc,
            "reset_start": board.reset_start,
            "sent": board.sent, "wire_fault": wire.code, "garbage_before": wire.garbage_before,
            "trunc_len": wire.trunc_len_per_sample,
            "slide_displacement_m": slide.displacement_m, "slide_velocity_mps": slide.velocity_mps,
            "slide_accel_mps2": slide.accel_mps2, "slide_segment": slide.segment, "aux": self._codes(aux_f), "aux_float": aux_f,
        }
        return _Chunk(arrays, wire)

    # ------------------------------------------------------------------ wire faults of a chunk
    def _wire_faults(self, ci: int, rng: np.random.Generator) -> _WireFaults:
        """Wire faults scheduled (faults.schedule_faults) in chunk ``ci``, per sample: fault code, garbage burst length
        (bytes) before it and nominal truncation length (bytes); the bit to flip, truncation lengths and garbage bytes
        are drawn from ``rng`` (the chunk's wire stream): frame faults in sample order, then garbage in sample order."""
        n = CHUNK
        wire_fault = np.zeros(n, np.int8)
        garbage_len = np.zeros(n, np.int64)
        flip_bit: dict[int, int] = {}
        trunc_len: dict[int, int] = {}
        garbage: dict[int, bytes] = {}
        k0 = ci * CHUNK
        for kk in self._wire_k[(self._wire_k >= k0) & (self._wire_k < k0 + CHUNK)].tolist():
            code = self.schedule.wire[kk]
            i = kk - k0
            wire_fault[i] = code
            if code == fz.BIT_FLIP:
                flip_bit[i] = int(rng.integers(0, 8 * (self.frame_size - fz.FLIP_FIRST_BYTE)))
            elif code == fz.TRUNCATE:
                trunc_len[i] = int(rng.integers(fz.TRUNC_MIN, self.frame_size))
        for kk in self._garbage_k[(self._garbage_k >= k0) & (self._garbage_k < k0 + CHUNK)].tolist():
            g = self.schedule.garbage[kk]
            garbage_len[kk - k0] = g
            garbage[kk - k0] = fz.garbage_bytes(rng, g)
        trunc_arr = np.zeros(n, np.int64)
        trunc_arr[list(trunc_len)] = list(trunc_len.values())
        return _WireFaults(wire_fault, garbage_len, trunc_arr, flip_bit, trunc_len, garbage)

    # ------------------------------------------------------------------ wire
    def _wire_pieces(self, ch: _Chunk, ci: int) -> list[bytes]:
        if ch.pieces is not None:
            return ch.pieces
        a = ch.arrays
        rec = fz.encode_frames(a["seq"], a["t_us"], a["counts"], a["temp_cc"], a["status"],
                               a["aux"] if self.protocol_version == 2 else None)
        raw = rec.tobytes()
        size = self.frame_size
        frames = [raw[i * size:(i + 1) * size] for i in range(CHUNK)]
        pieces: list[bytes] = []
        for i in range(CHUNK):
            g = ch.faults.garbage.get(i, b"")
            if not a["sent"][i]:
                pieces.append(b"")
                continue
            code = int(a["wire_fault"][i])
            fr = frames[i]
            if code == fz.DROP:
                body = b""
            elif code == fz.DUPLICATE:
                body = fr + fr
            elif code == fz.BIT_FLIP:
                bit = ch.faults.flip_bit[i]
                nbits = 8 * (size - fz.FLIP_FIRST_BYTE)
                for j in range(nbits):
                    cand = fz.corrupt_flip(fr, (bit + j) % nbits)
                    if not fz.hides_sync(cand):
                        body = cand
                        break
                else:  # pragma: no cover - impossible: flipping a bit inside an internal sync removes it
                    raise RuntimeError("no safe bit to flip")
            elif code == fz.TRUNCATE:
                body = self._safe_truncation(fr, ch.faults.trunc_len[i], frames, ch, i, size)
                ch.arrays["trunc_len"][i] = len(body)
            else:
                body = fr
            pieces.append(g + body)
        ch.pieces = pieces
        return pieces

    @staticmethod
    def _safe_truncation(fr: bytes, length: int, frames: list[bytes], ch: _Chunk, i: int, size: int) -> bytes:
        """A prefix of ``fr`` (>= 4 bytes) with no inner sync and whose ``size``-byte candidate window fails the CRC."""
        # Bytes that follow on the wire: garbage before the next sample + the next frame (guaranteed sent
        # and in the same chunk by the scheduler; a duplicate or fault on it only matters after the window).
        follow = ch.faults.garbage.get(i + 1, b"") + frames[i + 1] if i + 1 < CHUNK else b""
        for L in [length, *range(size - 1, fz.TRUNC_MIN - 1, -1)]:
            cand = fr[:L]
            if fz.hides_sync(cand):
                continue
            window = (cand + follow)[:size]
            if len(window) == size and crc16(window[2:size - 2]) == (window[size - 2] | (window[size - 1] << 8)):
                continue
            return cand
        raise RuntimeError("no safe truncation length")  # pragma: no cover

    # ------------------------------------------------------------------ counters
    def _count(self, a: dict[str, np.ndarray]) -> dict[str, int]:
        sent = a["sent"]
        wf = np.where(sent, a["wire_fault"], 0)
        flips = int((wf == fz.BIT_FLIP).sum())
        truncs = int((wf == fz.TRUNCATE).sum())
        c = {
            "injected_dropped": int((wf == fz.DROP).sum()),
            "injected_duplicates": int((wf == fz.DUPLICATE).sum()),
            "injected_bit_flips": flips,
            "injected_truncated": truncs,
            "injected_crc_errors": flips + truncs,
            "injected_garbage_bytes": int(a["garbage_before"][sent].sum()),
            "injected_garbage_bursts": int((a["garbage_before"][sent] > 0).sum()),
            "injected_resets": int(a["reset_start"].sum()),
            "unsent_frames": int((~sent).sum()),
            "saturated_samples": int(a["saturated"].any(axis=1).sum()),
            "temp_invalid_samples": int((~a["temp_valid"]).sum()),
            "expected_bytes_discarded": int(a["garbage_before"][sent].sum() + self.frame_size * flips
                                            + a["trunc_len"][sent & (wf == fz.TRUNCATE)].sum()),
        }
        deliver = sent & ~np.isin(wf, (fz.DROP, fz.BIT_FLIP, fz.TRUNCATE))
        rep = np.where(wf == fz.DUPLICATE, 2, 1)[deliver]
        self._expected.feed(np.repeat(a["seq"][deliver], rep), np.repeat(a["t_us"][deliver], rep),
                            np.repeat(a["status"][deliver], rep))
        for key, v in c.items():
            self.totals[key] = self.totals.get(key, 0) + v
        e = self._expected
        c.update({"total_expected_frames": e.frames, "total_expected_lost_frames": e.lost_frames,
                  "total_expected_duplicates": e.duplicates, "total_expected_resets": e.resets})
        return c


def simulate_recording(cfg: SimConfig | None = None, seed: int = 0, duration_s: float | None = None, run_id: int = 0):
    """Simulate a run and return what the calibration recorder would store (a ``Recording``).

    Samples that do not reach the host intact (dropped, corrupted, not sent) are absent; duplicates
    appear once. ``t_s`` is the board clock in seconds, continuous across board resets; ``temp_c`` is
    NaN where the AHT10 reading is not valid; ``gref_mps2`` is the table reference at the table's
    angle reading (defined while moving too); ``pose_id`` is -1 while the table moves. The truth of
    the kept samples is in ``metadata["truth"]``.
    """
    from fbg_accel_calibration.io.recording import Recording

    sim = BoardSimulator(cfg, seed=seed, wire=False)
    duration_s = duration_s if duration_s is not None else sim.duration_s
    if not math.isfinite(duration_s):
        raise ValueError("the scenario never ends (static pose or looping plan): pass duration_s")
    blk = sim.run(float(duration_s))
    a = blk.arrays
    keep = a["sent"] & ~np.isin(a["wire_fault"], (fz.DROP, fz.BIT_FLIP, fz.TRUNCATE))
    t_board = a["t_s"] * (1.0 + sim.clock_ppm * 1e-6)
    temp = np.where(a["temp_valid"], a["temp_sensor_c"], np.nan)
    eff = sim.cfg.get("effects")
    truth_keys = ("t_s", "accel_true_mps2", "temp_optics_c", "temp_chamber_c", "temp_sensor_true_c", "in_motion",
                  "psi_deg", "theta_deg", "time_at_pose_s", "visit", "counts_float", "saturated")
    meta = {
        "source": "board_sim", "config": sim.cfg.source, "seed": seed, "sensor_id": sim.cfg.get("sensor_id"),
        "rate_hz": sim.rate_hz, "effect_scales": {k: float(v["scale"]) for k, v in eff.items()},
        "aht10_offset_c": sim.aht_offset, "noise": {k: v for k, v in sim.configured_noise().items() if k != "model"},
        "truth": {k: a[k][keep] for k in truth_keys}, "fault_counters": dict(blk.counters),
    }
    return Recording(t_s=t_board[keep], ref=a["counts_float"][keep, 0], xyz=a["counts_float"][keep, 1:], temp_c=temp[keep],
                     gref_mps2=a["gref_mps2"][keep], pose_id=a["pose_id"][keep], run_id=np.full(int(keep.sum()), run_id),
                     metadata=meta, table_deg=np.column_stack([a["psi_deg"], a["theta_deg"]])[keep])
