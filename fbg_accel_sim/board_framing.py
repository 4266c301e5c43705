"""The board side of the simulator's frames (``board_physics``): the epochs between resets, the sequence number, the
board clock, the status bits, which samples are sent (boot gaps, disconnects) and the firmware's late reads
(firmware/core/fbg_scheduler.c)."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from fbg_accel_driver.frame_codec import SEQ_MODULO, Status

# firmware/core/fbg_scheduler.h FBG_SCHED_MAX_CATCH_UP: more reads due than this are skipped, not caught up
FIRMWARE_MAX_CATCH_UP = 4


class _Framing(NamedTuple):
    """Board side of the frames: board clock (s, us), sequence, status bits, sent flag, first sample after a reset."""

    board_t_s: np.ndarray
    t_us: np.ndarray
    seq: np.ndarray
    status: np.ndarray
    sent: np.ndarray
    reset_start: np.ndarray


class _BoardFraming:
    """Methods of :class:`~fbg_accel_sim.board_physics.BoardSimulator`, on its state (set up in its ``__init__``):
    resets, disconnects, late reads and the framing of each sample."""

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
