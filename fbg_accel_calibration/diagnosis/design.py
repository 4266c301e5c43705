"""The diagnosis's data and model: the samples it fits (``prepare_data``), a model as eq. 28 plus effects
(``ModelSpec``) and its design matrix, built from corrected inputs with what trials share kept (``DesignCache``).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..fit.static_detector import calibration_samples
from ..fit.thermal_fit import (
    design_matrix,
    n_params,
)
from ..io.recording import LowReference, Recording
from .data import (
    MIN_HELD_SAMPLES,
    DiagnosisData,
    Inputs,
    finite_rows,
    held_poses,
    memory_key,
    motion_groups,
    rows_at,
    visit_ids,
)
from .effects import Effect
from .search_lanes import beside
from .temperature_reading import reading_jumps

# ============================================================================ data preparation


SAMPLE_SELECTIONS = ("table", "detector", "all")


def _too_few_static(rec: Recording, n_use: int, static: str) -> str:
    """Why a recording has too few samples to diagnose (fewer than 20 fitted), in one line: above all, whether the
    table held any pose at all."""
    posed = int(np.count_nonzero(rec.pose_id >= 0))
    why = f"only {n_use} static samples with a reference (20 needed): nothing to diagnose"
    if posed == 0:
        return (f"{why}: no pose was held: every one of the {len(rec.pose_id)} samples was taken while the table "
                "moved; record with the table stopped at each pose")
    if static == "table":
        return (f"{why}: {posed} of the {len(rec.pose_id)} samples are at a held pose, but no pose was held for "
                f"{MIN_HELD_SAMPLES} samples in a row with a finite reference and unclipped channels")
    return f"{why} (sample selection {static!r}; {posed} of the {len(rec.pose_id)} samples at a held pose)"


def prepare_data(rec: Recording, static: str = "table", beside_thread: bool = False) -> DiagnosisData:
    """Diagnosis arrays from a recording. ``static`` selects the samples that are fitted and judged:

    * ``"table"`` (default): every sample of a pose the table held for at least ``MIN_HELD_SAMPLES`` (5) samples (the
      reference is known and constant). Chain dynamics that outlast the stop stay visible.
    * ``"detector"``: the fit's static-interval detector (signal still AND reference constant); it
      removes settling samples, so it hides most of the chain dynamics.
    * ``"all"``: every sample with a finite reference, including those taken while the table moves
      (only for recordings whose reference is the table's angle reading during motion, e.g. the
      simulator; samples in motion are cross-validated with the pose the table moves to).

    Whichever the selection, the samples of a reference too low (``Recording.low_reference``: no source light) are
    not in the result at all (counted in ``n_low_reference``, named in ``low_reference_note``), and a visit with a
    clipped channel is left out whole. ``beside_thread``: the temperature reading's jumps (a scan of every reading) are
    looked for on a thread of their own meanwhile the rest (``search_lanes.beside``).
    """
    if static not in SAMPLE_SELECTIONS:
        raise ValueError(f"static must be one of {SAMPLE_SELECTIONS}, got {static!r}")
    # the samples of a reference too low (no source light: Psi = counts/ref is no measurement) are taken out of the
    # recording first, as the fit takes them out (fit_stream.prepare_stream): the diagnosis of the recording without
    # them, whichever the selection, with a visit partly dark keeping its other samples
    dark = LowReference()
    dark.add_recording(rec)
    if dark.count:
        rec = rec.select(~rec.low_reference())
    jumps = beside(reading_jumps, rec.t_s, rec.temp_c, rec.run_id, thread=beside_thread)
    finite = finite_rows(rec.gref_mps2) & np.isfinite(rec.ref) & (rec.ref > 0)
    finite &= finite_rows(rec.xyz) & np.isfinite(rec.temp_c)
    # the visits with a channel at an ADC rail are left out whole, as the fit's detector leaves them out
    # (static_detector.clipped_visits), whichever the selection; and so is a clipped sample taken in motion
    visit, posed, at_rail = visit_ids(rec.pose_id, rec.run_id), rec.pose_id >= 0, rec.clipped()
    clipped = np.unique(visit[at_rail & posed])
    left_out = np.isin(visit, clipped) & posed
    finite &= ~(left_out | at_rail)
    if static == "all":
        use = finite & (motion_groups(rec.pose_id, rec.run_id) >= 0)
    elif static == "detector":
        usable, _ = calibration_samples(rec)
        use = usable & finite & (rec.pose_id >= 0)
    else:
        use = finite & held_poses(rec.pose_id, rec.run_id)
    if use.sum() < 20:
        raise ValueError(_too_few_static(rec, int(use.sum()), static))
    return DiagnosisData(rec.t_s, rec.ref, rec.xyz, rec.temp_c, rec.gref_mps2, rec.pose_id, rec.run_id, use,
                         group=visit, n_clipped_samples=int(left_out.sum()), n_clipped_visits=len(clipped),
                         n_low_reference=dark.count, low_reference_note=dark.warning(),
                         temperature_jumps=jumps.result(), table_deg=rec.table_deg)


# ============================================================================ model specification
@dataclass
class ModelSpec:
    """Declared degree + temperature scaling + the effects added so far, each with its hyper-parameter."""

    degree: int
    t_center_c: float
    t_scale_c: float
    effects: list[tuple[Effect, float | None]] = field(default_factory=list)

    def plus(self, effect: Effect, h: float | None) -> ModelSpec:
        return ModelSpec(self.degree, self.t_center_c, self.t_scale_c, [*self.effects, (effect, h)])

    @property
    def key(self) -> tuple:
        """What identifies the model: degree, temperature scaling, effects with their hyper-parameters."""
        return (self.degree, self.t_center_c, self.t_scale_c, tuple((e.name, h) for e, h in self.effects))

    @property
    def names(self) -> list[str]:
        return [e.name for e, _ in self.effects]


@dataclass
class Design:
    X: np.ndarray  # (N, p)
    G: np.ndarray  # (N, 3) reference (possibly re-aligned)
    valid: np.ndarray  # (N,) rows where X and G are finite and the effects are defined
    blocks: dict[str, slice]  # extra-column block of each effect
    n_base: int


def _transforms_inputs(eff: Effect) -> bool:
    return type(eff).transform is not Effect.transform


def _reads_every_sample(eff: Effect) -> bool:
    """Whether ``eff``'s columns read the corrected inputs of every sample (not only the design's rows)."""
    return type(eff).columns is not Effect.columns and not eff.pointwise


class _Recent(OrderedDict):
    """At most ``size`` entries once trimmed, the least recently used dropped first. Its methods hold a lock: the
    corrected references are shared by the lanes of a search (``DesignCache.for_another_lane``)."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = size
        self._lock = threading.Lock()

    def hit(self, key: tuple) -> Any:
        """The entry under ``key`` (made the most recent), or None."""
        with self._lock:
            value = self.get(key)
            if value is not None:
                self.move_to_end(key)
        return value

    def put(self, key: tuple, value: Any) -> None:
        with self._lock:
            self[key] = value

    def drop(self, which: Callable[[tuple], bool]) -> None:
        """Drop the entries whose key ``which`` says."""
        with self._lock:
            for key in [k for k in self if which(k)]:
                del self[key]

    def trim(self, room: int = 0) -> None:
        """Drop the oldest entries until ``room`` more fit: called with 1 before a new entry is computed, so that the
        arrays it replaces are not held beside the new ones while they are built."""
        with self._lock:
            while len(self) > self.size - room:
                self.popitem(last=False)


class DesignCache:
    """The corrected inputs of the last few sets of input corrections, the inputs part-way through the
    corrections (``prefix``) and the last few design matrices (bounded).

    A hyper-parameter search over an additive effect, and every candidate tried on top of the same model,
    feed eq. 28 the same corrected inputs: they are corrected once. A search over an input correction that
    runs after the model's own (a later stage) starts from the inputs the model's corrections left, instead
    of re-running them (the TIA correction filters the whole series on every trial). A correction of the
    reference alone (``Effect.reference_only``: the channel delay, the TIA low-pass) leaves the design matrix
    as it was: a search over one reuses the matrix, and ``cross_validate`` its sums. Only for one recording.
    """

    def __init__(self, size: int = 1, prefixes: int = 1, matrices: int = 2, references: int = 4) -> None:
        self.inputs = _Recent(size)  # (the inputs after a set of corrections, those at the design's rows)
        self.prefixes = _Recent(prefixes)  # the inputs after the first corrections of a set (``prefix``)
        self.matrices = _Recent(matrices)  # (X (n, p) read-only, its finite rows (n,), effect blocks) (``build_design``)
        self.references = _Recent(references)  # (reference (n, 3), valid rows (n,)) (``_corrected_reference``)
        self._taken = _Recent(8)

    def for_another_lane(self) -> DesignCache:
        """An empty cache of the same sizes for another lane (``search_lanes``) that shares this one's corrected
        references: each depends on its corrections and the design's rows alone, and a search over a correction of
        the reference tries the same grid whatever lane it runs on."""
        other = DesignCache(self.inputs.size, self.prefixes.size, self.matrices.size, 0)
        other.references = self.references
        return other

    def forget(self, name: str) -> None:
        """Drop what this lane's cache keeps of models with the effect ``name`` (its corrected inputs, prefixes and
        matrices, and the arrays it took rows of; the references it shares with other lanes stay): once a search over
        that effect on top of a model is judged, the trial values' series of 10^6 samples are of no use to the
        searches after it, and would stay beside their arrays until pushed out."""
        def named(key: tuple) -> bool:
            return any(isinstance(k, tuple) and (k[:1] == (name,) or named(k)) for k in key)

        for kept in (self.inputs, self.prefixes, self.matrices):
            kept.drop(named)
        self._taken.drop(lambda _: True)  # the rows taken of their arrays, which it holds: made again when asked

    def prefix(self, names: tuple) -> tuple[int, Inputs | None]:
        """(number of corrections done, a private copy of the inputs after them) for the longest cached prefix
        of ``names`` (the (name, hyper-parameter) of each correction in stage order); (0, None) if none."""
        for n in range(len(names) - 1, 0, -1):
            hit = self.prefixes.hit(names[:n])
            if hit is not None:
                return n, _private(hit)
        return 0, None

    def take(self, a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``a[idx]`` (``idx``: the rows of the cache's designs, the same on every call), kept for a read-only ``a``
        (the recorded inputs, a correction a search repeats unchanged, ``DiagnosisData.recent``) while it is among
        the last few such arrays asked for: most trials of a search change one input array and share the rest."""
        if a.flags.writeable:
            return rows_at(a, idx)
        key = memory_key(a)  # the same memory, read-only
        hit = self._taken.hit(key)
        if hit is None:
            hit = self._taken[key] = (a, rows_at(a, idx))  # a is kept: its memory cannot be reused for another array
            self._taken.trim()
        return hit[1]


def _private(inp: Inputs) -> Inputs:
    """A copy of ``inp`` that the corrections can work on without changing ``inp``: they replace its arrays
    and change only ``valid`` in place, so the other arrays are shared (read-only, ``Inputs.of``)."""
    return replace(inp, valid=inp.valid.copy())


def build_design(data: DiagnosisData, spec: ModelSpec, cache: DesignCache | None = None,
                 sub: np.ndarray | None = None) -> Design:
    """Regressors of eq. 28 on the corrected inputs, then the extra columns of the additive effects.

    The input corrections (``Effect.transform``) run first in stage order, on the whole time series; every
    effect's columns are then computed from the fully corrected inputs. ``sub`` (sample indices): the design
    of those rows only (the corrections still see every sample; eq. 28's columns and the columns of a
    ``pointwise`` effect are computed on those rows alone; where no effect's columns read other samples, the last
    correction may work out those rows alone, ``Effect.transform_rows``). ``cache`` keeps the corrected inputs of a set of
    corrections, and the design matrix of a model but for its corrections of the reference alone, for the
    next design that has the same (the arrays it holds are never written).
    """
    ordered = sorted(spec.effects, key=lambda eh: eh[0].stage)
    corrections = [(eff, h) for eff, h in ordered if _transforms_inputs(eff)]
    if cache is None:
        inp = _corrected_inputs(data, corrections)
        part = inp if sub is None else inp.at(sub)
        gref, valid = part.gref, part.valid
    else:
        # The corrections of the reference alone (Effect.reference_only) are worked out apart, with the corrections
        # before them: no other correction reads the reference, and they read only what comes before them.
        rows_only = sub is not None and not any(_reads_every_sample(e) for e, _ in ordered)
        inp, part = _corrected(data, [c for c in corrections if not c[0].reference_only], cache, sub, rows_only)
        gref, valid = part.gref, part.valid
        last = max((i + 1 for i, (e, _) in enumerate(corrections) if e.reference_only), default=0)
        if last:
            gref, ref_valid = _corrected_reference(data, corrections[:last], cache, sub)
            valid = valid & ref_valid
    # eq. 28's columns and the extra ones depend on every effect but the corrections of the reference alone
    x_key = (spec.degree, spec.t_center_c, spec.t_scale_c, tuple((e.name, h) for e, h in ordered if not e.reference_only))
    x_hit = cache.matrices.hit(x_key) if cache is not None else None
    if x_hit is None:
        if cache is not None:
            cache.matrices.trim(room=1)
        x_hit = _design_matrix(data, spec, ordered, inp, part, sub)
        if cache is not None:
            x_hit[0].flags.writeable = False  # shared by the designs of every trial value of a search over the reference
            cache.matrices[x_key] = x_hit
    X, x_ok, blocks = x_hit
    return Design(X, gref, valid & x_ok & finite_rows(gref), blocks, n_params(spec.degree))


def fitted_output(data: DiagnosisData, spec: ModelSpec, coeff: np.ndarray, block: int = 100_000) -> np.ndarray:
    """``build_design(data, spec).X @ coeff`` (N, k): the model's output on every sample, its design made ``block``
    rows at a time (the same rows' values) after the input corrections of the whole series: the design of every
    sample (N x p, 92 MiB at 10^6 samples) was the diagnosis's peak of memory, held beside the search's caches."""
    ordered = sorted(spec.effects, key=lambda eh: eh[0].stage)
    inp = _corrected_inputs(data, [(eff, h) for eff, h in ordered if _transforms_inputs(eff)])
    n = len(data.t_s)
    out = np.empty((n, coeff.shape[1]))
    for lo in range(0, n, block):
        rows = np.arange(lo, min(lo + block, n))
        out[rows[0]:rows[-1] + 1] = _design_matrix(data, spec, ordered, inp, inp.at(rows), rows)[0] @ coeff
    return out


def _corrected_inputs(data: DiagnosisData, corrections: list[tuple[Effect, float | None]]) -> Inputs:
    """The recording's inputs after ``corrections`` (input corrections in stage order), on every sample, uncached."""
    inp = Inputs.of(data)
    for eff, h in corrections:
        eff.transform(data, inp, h)
    return inp


def _corrected(data: DiagnosisData, corrections: list[tuple[Effect, float | None]], cache: DesignCache,
               sub: np.ndarray | None, rows_only: bool = False) -> tuple[Inputs | None, Inputs]:
    """(the inputs after ``corrections``, those at the design's rows ``sub``), from ``cache`` when it has them.
    ``rows_only``: nothing reads the corrected inputs but at ``sub``, so the last correction may correct those rows
    alone (``Effect.transform_rows``); the first is then None."""
    names = tuple((eff.name, h) for eff, h in corrections)
    on_rows = rows_only and sub is not None and bool(corrections)
    key = (*names, "rows") if on_rows else names  # a design that reads every sample needs the whole series
    hit = cache.inputs.hit(key)
    if hit is not None:
        return hit
    cache.inputs.trim(room=1)
    done, inp = cache.prefix(names)
    if inp is None:
        inp = Inputs.of(data)
    last = len(corrections) - 1
    for eff, h in corrections[done:last]:
        eff.transform(data, inp, h)
    if last > done:
        cache.prefixes[names[:last]] = _private(inp)  # all but the last: what a search over the last one repeats
        cache.prefixes.trim()

    def rows_of(inp: Inputs) -> Inputs:
        return inp if sub is None else inp.at(sub, lambda a: cache.take(a, sub))  # the design's rows

    if on_rows:
        eff, h = corrections[last]
        part = rows_of(inp)
        if eff.transform_rows(data, inp, part, h, sub):
            cache.inputs[key] = (None, part)
            return None, part
    if corrections:
        eff, h = corrections[last]
        eff.transform(data, inp, h)
    part = rows_of(inp)
    cache.inputs[key] = (inp, part)
    return inp, part


def _corrected_reference(data: DiagnosisData, corrections: list[tuple[Effect, float | None]], cache: DesignCache,
                         sub: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(the reference (n, 3) m/s^2 after ``corrections``, the rows (n,) they leave valid) at the design's rows
    ``sub``, from ``cache`` when it has them: a search over a correction of the reference tries the same grid
    for every model it is tried on top of."""
    names = tuple((eff.name, h) for eff, h in corrections)
    hit = cache.references.hit(names)
    if hit is None:
        inp = _reference_prefix(data, corrections[:-1], names[:-1], cache)
        last, h = corrections[-1]  # a correction of the reference alone (build_design): at the rows only
        hit = last.reference_at(data, inp, h, sub)
        for a in hit:
            a.flags.writeable = False
        cache.references.put(names, hit)
        cache.references.trim()
    return hit


def _reference_prefix(data: DiagnosisData, corrections: list[tuple[Effect, float | None]], names: tuple,
                      cache: DesignCache) -> Inputs:
    """A private copy (``_private``) of the inputs after ``corrections``, the ones before a correction of the reference
    alone, kept among the cache's ``prefixes`` (``names``: their (name, hyper-parameter)): every trial value of a
    search over that correction starts from the same inputs (a TIA low-pass of the model filters the whole series).
    The copy's counts are named by ``names`` (``Inputs.counts_of``): their expected Psi map is kept under them."""
    if not corrections:
        return Inputs.of(data)
    hit = cache.prefixes.hit(names)
    if hit is None:
        cache.prefixes.trim(room=1)
        hit = _corrected_inputs(data, corrections)
        cache.prefixes.put(names, hit)
    out = _private(hit)
    out.counts_of = (names, out.ref, out.xyz)  # their counts named by the corrections (``data.psi_map_of``)
    return out


def _design_matrix(data: DiagnosisData, spec: ModelSpec, ordered: list[tuple[Effect, float | None]],
                   inp: Inputs | None, part: Inputs,
                   sub: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, dict[str, slice]]:
    """(X (n, p): eq. 28's columns then each effect's, its finite rows (n,), each effect's block of columns) of
    ``build_design``: ``inp`` the corrected inputs (None: known at the design's rows alone, where no effect's columns
    read other samples), ``part`` those at the design's rows."""
    n_base = n_params(spec.degree)
    extra, blocks, p = [], {}, n_base
    for eff, h in ordered:
        c = eff.columns(data, part, h) if eff.pointwise else eff.columns_at(data, inp, h, sub)
        if c is not None:
            blocks[eff.name] = slice(p, p + c.shape[1])
            extra.append(c)
            p += c.shape[1]
    X = np.empty((p, len(part.valid))).T  # column-major, filled in place: no concatenation copy
    tau = (part.temp_c - spec.t_center_c) / spec.t_scale_c
    # the recorded counts at the design's rows: their Psi kept for the search's rows (``DiagnosisData.psi_at``)
    recorded = sub is not None and part.index is sub and not part.counts_changed
    design_matrix(data.psi_at(sub) if recorded else part.psi, tau, spec.degree, out=X[:, :n_base])
    ok = finite_rows(X[:, :n_base])
    for c, sl in zip(extra, blocks.values(), strict=True):
        X[:, sl] = c
        ok &= finite_rows(c)
    return X, ok, blocks
