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

from fbg_accel_calibration.io.table_geometry import table_specific_force
from fbg_accel_driver.adc_code_table import pattern_codes
from fbg_accel_driver.frame_codec import BODY_LEN_BY_VERSION, SEQ_MODULO, Frame, Status, crc16, frame_size

from . import faults as fz
from .noise import GaussMarkovBank, NoiseModel, first_order_filter
from .optics import STANDARD_G, PairOverlap, grating_sigma_nm, relative_response, source_factor
from .scenario import TemperatureProfile, build_slide, build_trajectory, second_order_response, vibration
from .sim_config import SimConfig

CHUNK = 2048  # samples per generation chunk (fixed: determinism does not depend on step sizes)
# firmware/core/fbg_scheduler.h FBG_SCHED_MAX_CATCH_UP: more reads due than this are skipped, not caught up
FIRMWARE_MAX_CATCH_UP = 4
CHANNELS = ("ref", "x", "y", "z")
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


def _first_order(x: np.ndarray, alpha: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y[k] = alpha y[k-1] + (1 - alpha) x[k] along axis 0 (columns independent); returns (y, new state)."""
    if alpha <= 0.0:
        return x.copy(), np.atleast_1d(x[-1]).copy()
    y = first_order_filter(x, alpha, -math.expm1(math.log(alpha)), np.asarray(state, float).reshape(x.shape[1:]))
    return y, np.atleast_1d(y[-1]).copy()


def _lowpass(x: np.ndarray, tau_s: float, dt_s: float, y_prev: float, x_prev: float,
             linear: bool) -> tuple[np.ndarray, float, float]:
    """First-order low-pass 1/(1 + s tau) of a 1-D sampled signal; returns (y, last y, last x).

    ``linear``: exact response to an input linear between samples (first-order hold, no phase error);
    else the input is held over each interval (y[k] = a y[k-1] + (1 - a) x[k]). ``tau_s`` 0: y = x.
    """
    x = np.asarray(x, float)
    if tau_s <= 0.0:
        return x.copy(), float(x[-1]), float(x[-1])
    a = math.exp(-dt_s / tau_s)
    if linear:
        r = tau_s / dt_s * -math.expm1(-dt_s / tau_s)  # tau/dt (1 - a)
        prev = np.concatenate([[x_prev], x[:-1]])
        v = (1.0 - r) * x + (r - a) * prev
        y = first_order_filter(v, a, 1.0, y_prev)
    else:
        y = first_order_filter(x, a, -math.expm1(-dt_s / tau_s), y_prev)
    return y, float(y[-1]), float(x[-1])


def _play_branch(x: np.ndarray, width: float, p: float) -> tuple[np.ndarray, float]:
    """Branch (x - play(x)) / width in [-1/2, 1/2] of a play operator (backlash of ``width``, in the unit of ``x``) that
    starts at ``p``, and its last output: +1/2 after a rise of ``x`` by more than the width, -1/2 after a fall, in
    between on a reversal smaller than the width. Zeros when ``width`` is 0."""
    u_play = np.empty(x.shape[0])
    half = 0.5 * width
    for i, v in enumerate(x.tolist()):
        if v - p > half:
            p = v - half
        elif p - v > half:
            p = v + half
        u_play[i] = p
    return ((x - u_play) / width if width > 0 else np.zeros(x.shape[0])), p


class _TableMotion(NamedTuple):
    """Table stage of a chunk: readings at t, and what the seismic mass feels (arrays over the samples)."""

    psi_deg: np.ndarray  # table angle readings at t (deg)
    theta_deg: np.ndarray
    pose_id: np.ndarray
    in_motion: np.ndarray
    visit: np.ndarray
    time_at_pose_s: np.ndarray
    gref_mps2: np.ndarray  # (N, 3) table reference specific force at the reading (m/s^2)
    accel_true_mps2: np.ndarray  # (N, 3) true specific force at t, sensor frame (m/s^2)
    felt_mps2: np.ndarray  # (N, 3) felt by the mass: at t - delay, dynamic parts through the resonance (m/s^2)
    psi_felt_deg: np.ndarray  # inner angle at t - delay (deg): drives the cable torque


class _Slide(NamedTuple):
    """True linear-slide motion along its direction (arrays over the samples; segment -1 = at rest or no slide)."""

    displacement_m: np.ndarray
    velocity_mps: np.ndarray
    accel_mps2: np.ndarray
    segment: np.ndarray


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


class _Framing(NamedTuple):
    """Board side of the frames: board clock (s, us), sequence, status bits, sent flag, first sample after a reset."""

    board_t_s: np.ndarray
    t_us: np.ndarray
    seq: np.ndarray
    status: np.ndarray
    sent: np.ndarray
    reset_start: np.ndarray


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


class BoardSimulator:
    """Streaming simulator of the board: ``step(n) -> SimBlock`` (deterministic for a seed)."""

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

    def _sensed_force(self, tt: np.ndarray) -> np.ndarray:
        """Specific force (N, 3) m/s^2, sensor frame, that the seismic mass feels at times ``tt`` (s): table
        gravity + vibration + slide, dynamic parts through the mechanical resonance."""
        psi, theta, *_ = self.trajectory.evaluate(tt)
        f = table_specific_force(psi, theta, self.gravity) @ self.R_mount.T + vibration(tt, self.sines, self.resonance)
        if self.slide is not None:
            f = f + self.slide.kinematics(tt, self.resonance)[2][:, None] * self.slide.direction[None, :]
        return f

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

    def _setup_late_reads(self, spec: dict[str, Any]) -> None:
        """``faults.late_reads``: the sampler misses a deadline and the firmware catches up, as
        firmware/core/fbg_scheduler.c ``fbg_sched_take`` with firmware/host/fbg_board_host.c ``--late``: the read at
        each ``at_s`` is taken ``late_s`` late; each following read starts when it is due or when the previous read is
        done (``read_s`` later), whichever is later, until one is on time again. A read taken at or after the next
        read's due time carries ADC_OVERRUN. Nothing is lost (``late_s`` must stay below FBG_SCHED_MAX_CATCH_UP
        periods: the firmware's skip-ahead is not modelled). Stored per sample index: how late (board s) it is read."""
        period = 1.0 / self.rate_hz
        late_s, read_s = float(spec.get("late_s", 0.0)), float(spec.get("read_s", 4e-5))
        at = sorted(float(t) for t in (spec.get("at_s") or []))
        offsets: dict[int, float] = {}
        overrun: set[int] = set()
        if at and not (0.0 < late_s < FIRMWARE_MAX_CATCH_UP * period and 0.0 < read_s < period):
            raise ValueError(f"faults.late_reads: late_s must be in (0, {FIRMWARE_MAX_CATCH_UP} periods) and read_s in "
                             f"(0, 1 period), got {late_s!r}, {read_s!r}")
        for t in at:
            k, off = math.ceil(t * self.rate_true_hz - 1e-9), late_s
            while off > 0.0:  # late by off: read at k P + off; the next read starts read_s after it, if it is due
                offsets[k] = max(off, offsets.get(k, 0.0))  # two events on one read: the later one
                if off >= period:
                    overrun.add(k)
                off += read_s - period
                k += 1
        self._late_k = np.array(sorted(offsets), dtype=np.int64)
        self._late_off_s = np.array([offsets[k] for k in self._late_k.tolist()], dtype=float)
        self._overrun_k = np.array(sorted(overrun), dtype=np.int64)

    def _late_offsets(self, k: np.ndarray) -> np.ndarray:
        """How late (board s) each sample ``k`` (consecutive indices) is read (faults.late_reads; 0 on time)."""
        off = np.zeros(k.shape[0])
        if self._late_k.size:
            sel = (self._late_k >= k[0]) & (self._late_k <= k[-1])
            off[self._late_k[sel] - k[0]] = self._late_off_s[sel]
        return off

    def _first_sent_k(self, start: int, end: int) -> int:
        """First sample index in [start, end) outside every disconnect window, or -1."""
        k, moved = start, True
        while moved:
            moved = False
            for a0, b0 in self._disc_k:
                if a0 <= k < b0:
                    k, moved = b0, True
        return k if k < end else -1

    def _unsent(self, k: np.ndarray | int) -> np.ndarray:
        """Whether the board never sends sample(s) ``k``: in the boot gap after a reset, or in a disconnect window."""
        out = np.zeros(np.shape(k), bool)
        for r in self.reset_k:
            out |= (k >= r) & (k < r + self.gap_n)
        for a0, b0 in self._disc_k:
            out |= (k >= a0) & (k < b0)
        return out

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

    def _codes(self, x: np.ndarray) -> np.ndarray:
        """ADC codes (int64, 0..adc_max) of counts ``x`` before the integer conversion."""
        return np.clip(np.round(x), 0, self.adc_max).astype(np.int64)

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

    # ------------------------------------------------------------------ stages of the signal chain
    def _table_motion(self, t: np.ndarray, delay: float) -> _TableMotion:
        """Table angle readings at ``t`` (s, deg) and the specific force (m/s^2, sensor frame) the seismic mass feels
        ``delay`` s later (channel_delay effect, ASSUMPTION): gravity through the table geometry and the mount rotation
        plus the vibration sines, whose dynamic part goes through the mechanical resonance (paper 3.4, facts)."""
        psi, theta, pose_id, moving, visit = self.trajectory.evaluate(t)
        arrival = self.trajectory.arrival_time(t)
        gref = table_specific_force(psi, theta, self.gravity)
        vib_true = vibration(t, self.sines)
        if delay != 0.0:
            psi_d, theta_d, *_ = self.trajectory.evaluate(t - delay)
            f_phys_table = table_specific_force(psi_d, theta_d, self.gravity)
        else:
            psi_d, f_phys_table = psi, gref
        vib_phys = vibration(t - delay, self.sines, self.resonance) if delay != 0.0 or self.resonance else vib_true
        accel_true = gref @ self.R_mount.T + vib_true
        f_phys = f_phys_table @ self.R_mount.T + vib_phys
        return _TableMotion(psi, theta, pose_id, moving, visit, arrival, gref, accel_true, f_phys, psi_d)

    def _linear_slide(self, t: np.ndarray, delay: float, table: _TableMotion) -> tuple[_Slide, _TableMotion]:
        """Linear slide of a dynamic calibration (seed 2, section 2): its true motion at ``t`` along the slide direction
        (m, m/s, m/s^2; truth and reference transducer) and ``table`` with the slide's acceleration added, true at ``t``
        and felt at ``t - delay`` through the resonance (m/s^2). Without a slide: zeros, segment -1, ``table`` as is."""
        if self.slide is None:
            zero = np.zeros(t.shape[0])
            return _Slide(zero, zero, zero, np.full(t.shape[0], -1, dtype=np.int64)), table
        sl_x, sl_v, sl_a = self.slide.kinematics(t)
        accel_true = table.accel_true_mps2 + sl_a[:, None] * self.slide.direction[None, :]
        felt = table.felt_mps2 + self.slide.kinematics(t - delay, self.resonance)[2][:, None] * self.slide.direction[None, :]
        return (_Slide(sl_x, sl_v, sl_a, self.slide.segment_index(t)),
                table._replace(accel_true_mps2=accel_true, felt_mps2=felt))

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

    def _axis_biases(self, t: np.ndarray, T_opt: np.ndarray, psi_felt_deg: np.ndarray, felt: np.ndarray) -> np.ndarray:
        """Equivalent acceleration biases (N, 3) on the axis inputs, m/s^2: time drift (warm-up and creep of the pair
        separation: bond relaxation, not characterised in the paper), thermal hysteresis (bond/mount stress; play
        operator on the optics temperature ``T_opt``, degC), a step of the bias at one time (``bias_step``: the calibration
        stops holding, what the driver's gravity check must see) and the unmodelled cable torque ~ sin(harmonic psi) (fibre
        pigtail drag at the felt inner angle ``psi_felt_deg``) and a motion-history hysteresis (each axis' branch set by the
        sign of the last change of the specific force it feels, ``felt`` (N, 3) m/s^2); amplitudes ASSUMPTION
        (config/sim_default.yaml)."""
        eff = self.cfg.get("effects")
        bias = np.zeros((t.shape[0], 3))
        td = eff["time_drift"]
        if float(td["scale"]) != 0.0:
            w = np.asarray(td["warmup_amplitude_mps2"], float) * -np.expm1(-t / float(td["warmup_time_constant_s"]))[:, None]
            bias += float(td["scale"]) * (w + np.asarray(td["creep_mps2_per_h"], float) * (t / 3600.0)[:, None])
        hy = eff["thermal_hysteresis"]
        if float(hy["scale"]) != 0.0:
            branch = self._hysteresis_branch(T_opt, float(hy["play_width_c"]))
            bias += float(hy["scale"]) * branch[:, None] * np.asarray(hy["amplitude_mps2"], float)
        bs = eff["bias_step"]
        if float(bs["scale"]) != 0.0:  # the response steps once after calibration (a knock, a mount shift; ASSUMPTION)
            bias += float(bs["scale"]) * (t >= float(bs["at_s"]))[:, None] * np.asarray(bs["amplitude_mps2"], float)
        ct = eff["unmodelled_cable_torque"]
        if float(ct["scale"]) != 0.0:
            ang = np.radians(float(ct["harmonic"]) * psi_felt_deg + float(ct["phase_deg"]))
            bias += float(ct["scale"]) * np.sin(ang)[:, None] * np.asarray(ct["amplitude_mps2"], float)
        mh = eff["motion_hysteresis"]
        if float(mh["scale"]) != 0.0:  # friction in the suspension and bonds (ASSUMPTION): the force's last change
            branch = self._motion_branches(felt, float(mh["play_width_mps2"]))
            bias += float(mh["scale"]) * branch * np.asarray(mh["amplitude_mps2"], float)
        return bias

    def _hysteresis_branch(self, T_opt: np.ndarray, width: float) -> np.ndarray:
        """Thermal hysteresis branch in [-1/2, 1/2] (``_play_branch`` of the optics temperature, ``width`` degC), the
        play operator's output kept in ``self._play`` from chunk to chunk."""
        branch, self._play = _play_branch(T_opt, width, self._play)
        return branch

    def _motion_branches(self, felt: np.ndarray, width: float) -> np.ndarray:
        """Motion-history branch (N, 3) in [-1/2, 1/2] of each axis: ``_play_branch`` of the specific force the axis
        feels (``felt``, m/s^2, sensor frame; ``width`` m/s^2), so it is set by the sign of the force's last change
        larger than the width; the play operators' outputs carry from chunk to chunk."""
        if self._force_play is None:
            self._force_play = np.array(felt[0], dtype=float)
        out = np.empty_like(felt)
        for j in range(3):
            out[:, j], self._force_play[j] = _play_branch(felt[:, j], width, float(self._force_play[j]))
        return out

    def _axis_inputs(self, t: np.ndarray, delay: float, felt: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """Axis inputs u = A f + bias (N, 3), m/s^2, with A the cross-axis coupling derived from the published
        calibration matrix (paper eq. 31a). With a channel skew (board.adc_channel_skew_us), the ESP32 one-shot
        sequential conversion (ESP-IDF adc_oneshot_read) makes each axis see its own, later instant."""
        u = felt @ self.A.T + bias
        if self.skew_s > 0.0 or np.any(self.channel_extra_delay_s):
            # ESP32 one-shot sequential conversion: axis channel j (x, y, z = 1, 2, 3 after ref) is converted
            # j skews after t_us, so it sees the input of that later instant (an LTI chain commutes with the shift);
            # an axis channel's own extra delay (axis_channel_extra_s) moves it the other way
            for j in range(3):
                u[:, j] = self._sensed_force(self._channel_time(t, delay, j)) @ self.A[j] + bias[:, j]
        return u

    def _channel_time(self, t: np.ndarray, delay: float, j: int) -> np.ndarray:
        """The instant (s) axis channel ``j`` (0..2: x, y, z) senses at sample time ``t``: the common channel delay,
        the channel's own extra delay and its ADC conversion skew."""
        return t - delay - float(self.channel_extra_delay_s[j]) + (j + 1) * self.skew_s

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

    def _board_framing(self, k: np.ndarray, t: np.ndarray, present: np.ndarray, valid: np.ndarray,
                       late: np.ndarray) -> _Framing:
        """Board side of each sample ``k`` (true time ``t``, s): epoch between resets (faults.resets), sequence number,
        board clock t_us (crystal error board.clock_ppm; restarts at each reset), status bits (docs/protocol.md) and
        whether it is sent at all (not during a boot gap, board.boot_gap_s, nor a disconnect); BOOT on the first sample
        of each epoch that is sent (``boot_k``)."""
        epoch = np.searchsorted(self.epoch_start, k, side="right") - 1
        start = self.epoch_start[epoch]
        seq = (k - start) % SEQ_MODULO
        reset_t = np.concatenate([[0.0], self.reset_k * self.dt_true])
        t_epoch0 = reset_t[epoch]
        board_t = np.where(epoch > 0, (t - t_epoch0) * (1.0 + self.clock_ppm * 1e-6), k / self.rate_hz + late)
        t_us = np.round(board_t * 1e6).astype(np.int64)
        sent = ~self._unsent(k)
        status = np.where(present, int(Status.TEMP_PRESENT), 0) | np.where(valid, int(Status.TEMP_VALID), 0)
        status = status | np.where(k == self.boot_k[epoch], int(Status.BOOT), 0)  # first SENT frame of the epoch
        for wdw in self.windows["adc_overrun"]:
            status = status | np.where(self._inside(t, wdw), int(Status.ADC_OVERRUN), 0)
        status = status | np.where(np.isin(k, self._overrun_k), int(Status.ADC_OVERRUN), 0)  # faults.late_reads
        return _Framing(board_t, t_us, seq, status.astype(np.int64), sent, (k == start) & (epoch > 0))

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
