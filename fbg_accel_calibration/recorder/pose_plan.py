"""Pose plan of a multi-position calibration run: load and validate its YAML (pure, no ROS).

A pose plan lists the orientations a rotation table holds during one calibration run, the
local gravity, how long the table dwells at each pose and how many samples the calibration
node records per pose; optionally the climatic-chamber set-points of the temperature levels
at which the plan is repeated (one run, one MCAP file per level). The format is documented in
``docs/calibration_node.md``; example plans are ``config/pose_plan_six_position.yaml`` and
``test/fixtures/pose_plan_sim_e2e.yaml`` (a test fixture). The board simulator's pose-plan scenario reads the same
file, so the simulated table and the node follow the same angles and dwell times.

Each pose gives its reference either as table angles ``psi_deg``/``theta_deg`` (degrees, the
convention of ``table_geometry``: f = Rz(psi)^T Rx(theta)^T (0, 0, g)) or directly as the
reference specific force ``gref_mps2`` (3 values, m/s^2, table frame). At rest on a table the
specific force has magnitude g, so a ``gref_mps2`` whose norm is off the plan's local g by more
than ``GREF_NORM_TOLERANCE`` is refused (it is almost always a unit slip, g instead of m/s^2). Likewise
table angles in radians: a plan whose angles are all within 2 pi, some near a non-zero multiple of pi/2,
and whose references all lie within ``RADIAN_SPREAD_DEG`` of each other is refused.

Every problem raises ``PosePlanError`` with one message naming the file and the offending key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fbg_accel_driver.mapping_fields import format_version, number
from fbg_accel_driver.yaml_input import YamlFileError, read_yaml_file

from ..io.table_geometry import STANDARD_GRAVITY, table_specific_force

FORMAT_NAME = "fbg_accel_pose_plan"
FORMAT_VERSION = 1
GREF_NORM_TOLERANCE = 0.01  # relative; |gref| must be within 1 % of the plan's local g
LOCAL_G_RANGE_MPS2 = (9.76, 9.84)  # gravity on the Earth's surface spans about 9.764 (equator, high) to 9.834 (poles)
CHAMBER_RANGE_C = (-70.0, 180.0)  # widest range of common climatic chambers; outside is a typo
DEFAULT_SAMPLES_PER_POSE = 100  # paper section 4.5: 100 samples per pose
RADIAN_ANGLE_TOLERANCE = 0.01  # rad; an angle this close to a multiple of pi/2 looks like radians
RADIAN_SPREAD_DEG = 15.0  # deg; a plan whose references all lie this close to each other is no calibration
DEFAULT_MOVE_S = 5.0  # s, time the table takes between two poses (only the simulator's scenario uses it)

_TOP_KEYS = {"format", "format_version", "name", "description", "local_g_mps2", "samples_per_pose", "dwell_s", "move_s",
             "chamber", "poses"}
_POSE_KEYS = {"name", "psi_deg", "theta_deg", "gref_mps2", "dwell_s", "samples"}
_CHAMBER_KEYS = {"levels_c", "soak_s", "tolerance_c"}


class PosePlanError(ValueError):
    """A pose plan file is missing, malformed or physically impossible."""


@dataclass(frozen=True)
class Pose:
    """One static pose: its reference specific force ``gref_mps2`` (3,) in m/s^2 (table frame).

    ``psi_deg``/``theta_deg`` are the table angles when the pose was given as angles (else None).
    ``dwell_s`` is how long the table holds the pose (s); ``samples`` how many samples to record.
    """

    index: int
    name: str
    gref_mps2: np.ndarray
    dwell_s: float
    samples: int
    psi_deg: float | None = None
    theta_deg: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """As given: table angles, else the reference."""
        given = ({"psi_deg": self.psi_deg, "theta_deg": self.theta_deg} if self.psi_deg is not None
                 and self.theta_deg is not None else {"gref_mps2": [float(v) for v in self.gref_mps2]})
        return {"name": self.name, **given, "dwell_s": self.dwell_s, "samples": self.samples}


@dataclass(frozen=True)
class ChamberPlan:
    """Climatic-chamber set-points (degC), one run per level; ``soak_s`` settling time per level (s),
    ``tolerance_c`` how far the sensor temperature may sit from the set-point before a run warns."""

    levels_c: tuple[float, ...]
    soak_s: float = 0.0
    tolerance_c: float = 2.0


@dataclass(frozen=True)
class PosePlan:
    """A validated pose plan (see the module docstring)."""

    name: str
    poses: tuple[Pose, ...]
    local_g_mps2: float = STANDARD_GRAVITY
    move_s: float = DEFAULT_MOVE_S
    chamber: ChamberPlan | None = None
    description: str = ""
    source: str = "<dict>"
    raw: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def gref_mps2(self) -> np.ndarray:
        """(P, 3) reference specific force of every pose, m/s^2."""
        return np.array([p.gref_mps2 for p in self.poses])

    @property
    def total_samples(self) -> int:
        return sum(p.samples for p in self.poses)

    def nominal_duration_s(self) -> float:
        """Time the table needs for one pass: every dwell plus a move between consecutive poses (s)."""
        return sum(p.dwell_s for p in self.poses) + self.move_s * max(len(self.poses) - 1, 0)

    def level_setpoint_c(self, level: int) -> float | None:
        """Chamber set-point of temperature level ``level`` (0-based), None for ``level < 0``."""
        if level < 0:
            return None
        if self.chamber is None:
            raise PosePlanError(f"{self.source}: temperature level {level} requested but the plan has no 'chamber' section")
        if level >= len(self.chamber.levels_c):
            raise PosePlanError(f"{self.source}: temperature level {level} requested but the plan has "
                                f"{len(self.chamber.levels_c)} levels (0..{len(self.chamber.levels_c) - 1})")
        return self.chamber.levels_c[level]

    def to_dict(self) -> dict[str, Any]:
        """Plain, normalised form (every pose explicit) for run metadata."""
        d: dict[str, Any] = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "name": self.name,
                             "description": self.description, "local_g_mps2": self.local_g_mps2, "move_s": self.move_s,
                             "poses": [p.to_dict() for p in self.poses]}
        if self.chamber is not None:
            d["chamber"] = {"levels_c": list(self.chamber.levels_c), "soak_s": self.chamber.soak_s,
                            "tolerance_c": self.chamber.tolerance_c}
        return d

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def load(cls, path: str | Path) -> PosePlan:
        p = Path(path)
        try:
            data = read_yaml_file(p, "pose plan file")
        except YamlFileError as exc:
            raise PosePlanError(str(exc)) from None
        return cls.from_dict(data, source=str(p))

    @classmethod
    def from_dict(cls, d: Any, source: str = "<dict>") -> PosePlan:
        return _parse(d, source)


# ---------------------------------------------------------------------------------------- parsing
def _count(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise PosePlanError(f"{where} must be a positive integer, got {value!r}")
    return int(value)


def _unknown(keys: set[str], allowed: set[str], where: str) -> None:
    extra = sorted(keys - allowed)
    if extra:
        raise PosePlanError(f"{where}: unknown key(s) {extra}; allowed: {sorted(allowed)}")


def _parse(d: Any, source: str) -> PosePlan:
    if not isinstance(d, dict):
        raise PosePlanError(f"{source}: top level is not a mapping")
    _unknown(set(map(str, d)), _TOP_KEYS, source)
    if d.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise PosePlanError(f"{source}: format is {d['format']!r}, expected '{FORMAT_NAME}'")
    format_version(d.get("format_version", FORMAT_VERSION), "format_version", lambda m: PosePlanError(f"{source}: {m}"),
                   reads=FORMAT_VERSION, reader="this tool")
    name = str(d.get("name", Path(source).stem))
    g = number(d.get("local_g_mps2", STANDARD_GRAVITY), f"{source}: local_g_mps2", PosePlanError)
    if not LOCAL_G_RANGE_MPS2[0] <= g <= LOCAL_G_RANGE_MPS2[1]:
        raise PosePlanError(f"{source}: local_g_mps2 = {g} m/s^2 is not a gravity on the Earth's surface "
                            f"({LOCAL_G_RANGE_MPS2[0]}..{LOCAL_G_RANGE_MPS2[1]}); is it in m/s^2?")
    default_samples = _count(d.get("samples_per_pose", DEFAULT_SAMPLES_PER_POSE), f"{source}: samples_per_pose")
    default_dwell = number(d["dwell_s"], f"{source}: dwell_s", PosePlanError, positive=True) if "dwell_s" in d else None
    move_s = number(d.get("move_s", DEFAULT_MOVE_S), f"{source}: move_s", PosePlanError, minimum=0.0)

    raw_poses = d.get("poses")
    if not isinstance(raw_poses, list) or not raw_poses:
        raise PosePlanError(f"{source}: 'poses' must be a non-empty list")
    poses: list[Pose] = []
    names: set[str] = set()
    for i, rp in enumerate(raw_poses):
        where = f"{source}: poses[{i}]"
        if not isinstance(rp, dict):
            raise PosePlanError(f"{where} is not a mapping")
        _unknown(set(map(str, rp)), _POSE_KEYS, where)
        pname = str(rp.get("name", f"pose_{i}"))
        if pname in names:
            raise PosePlanError(f"{where}: duplicate pose name {pname!r}")
        names.add(pname)
        has_angles = "psi_deg" in rp or "theta_deg" in rp
        has_gref = "gref_mps2" in rp
        if has_angles and has_gref:
            raise PosePlanError(f"{where} ({pname}): give either psi_deg/theta_deg or gref_mps2, not both")
        psi = theta = None
        if has_angles:
            if "psi_deg" not in rp or "theta_deg" not in rp:
                raise PosePlanError(f"{where} ({pname}): table angles need both psi_deg and theta_deg")
            psi = number(rp["psi_deg"], f"{where}.psi_deg", PosePlanError)
            theta = number(rp["theta_deg"], f"{where}.theta_deg", PosePlanError)
            gref = table_specific_force(np.array([psi]), np.array([theta]), g)[0]
            gref = np.where(np.abs(gref) < 1e-12 * g, 0.0, gref)  # exact zeros for axis-aligned poses
        elif has_gref:
            vec = rp["gref_mps2"]
            if not isinstance(vec, list) or len(vec) != 3:
                raise PosePlanError(f"{where}.gref_mps2 must be a list of 3 numbers (m/s^2), got {vec!r}")
            gref = np.array([number(v, f"{where}.gref_mps2[{k}]", PosePlanError) for k, v in enumerate(vec)])
            norm = float(np.linalg.norm(gref))
            if abs(norm - g) > GREF_NORM_TOLERANCE * g:
                raise PosePlanError(f"{where} ({pname}): |gref_mps2| = {norm:.4f} m/s^2 but a static pose senses local g "
                                    f"= {g} m/s^2 (tolerance {GREF_NORM_TOLERANCE:.0%}); values must be in m/s^2")
        else:
            raise PosePlanError(f"{where} ({pname}): needs table angles psi_deg/theta_deg or a reference gref_mps2")
        if "dwell_s" not in rp and default_dwell is None:
            raise PosePlanError(f"{where} ({pname}): no dwell time: set the pose's or the plan's 'dwell_s' (s)")
        dwell = number(rp.get("dwell_s", default_dwell), f"{where}.dwell_s", PosePlanError, positive=True)
        samples = _count(rp.get("samples", default_samples), f"{where}.samples")
        poses.append(Pose(i, pname, gref, dwell, samples, psi, theta))

    _refuse_radians(poses, source)
    chamber = None
    if d.get("chamber") is not None:
        chamber = _parse_chamber(d["chamber"], f"{source}: chamber")
    return PosePlan(name=name, poses=tuple(poses), local_g_mps2=g, move_s=move_s, chamber=chamber,
                    description=str(d.get("description", "")), source=source, raw=dict(d))


def _refuse_radians(poses: list[Pose], source: str) -> None:
    """Refuse table angles that look like radians written into the ``*_deg`` keys (pi, pi/2, ...): the
    references then all lie within a few degrees of each other and the run calibrates against wrong
    references, as a ``gref_mps2`` in g would (which is refused by its norm)."""
    angled = [p for p in poses if p.psi_deg is not None]
    if len(angled) < 2:
        return
    angles = np.array([a for p in angled for a in (p.psi_deg, p.theta_deg)], dtype=float)
    if np.any(np.abs(angles) > 2 * np.pi + RADIAN_ANGLE_TOLERANCE):
        return
    quarter = angles / (np.pi / 2)
    near = (np.abs(quarter - np.round(quarter)) * (np.pi / 2) < RADIAN_ANGLE_TOLERANCE) & (np.round(quarter) != 0)
    if not np.any(near):
        return
    unit = np.array([p.gref_mps2 / np.linalg.norm(p.gref_mps2) for p in angled])
    spread = float(np.degrees(np.arccos(np.clip(unit @ unit.T, -1.0, 1.0))).max())
    if spread < RADIAN_SPREAD_DEG:
        shown = ", ".join(f"{a:g}" for a in angles[near][:4])
        raise PosePlanError(f"{source}: the table angles look like radians ({shown} are near multiples of pi/2) and "
                            f"all poses lie within {spread:.1f} deg of each other; psi_deg/theta_deg are in degrees")


def _parse_chamber(c: Any, where: str) -> ChamberPlan:
    if not isinstance(c, dict):
        raise PosePlanError(f"{where} is not a mapping")
    _unknown(set(map(str, c)), _CHAMBER_KEYS, where)
    levels = c.get("levels_c")
    if not isinstance(levels, list) or not levels:
        raise PosePlanError(f"{where}.levels_c must be a non-empty list of set-points (degC)")
    out = []
    for k, v in enumerate(levels):
        t = number(v, f"{where}.levels_c[{k}]", PosePlanError)
        if not CHAMBER_RANGE_C[0] <= t <= CHAMBER_RANGE_C[1]:
            raise PosePlanError(f"{where}.levels_c[{k}] = {t} degC is outside {CHAMBER_RANGE_C} degC; is it in degC?")
        out.append(t)
    soak = number(c.get("soak_s", 0.0), f"{where}.soak_s", PosePlanError, minimum=0.0)
    tol = number(c.get("tolerance_c", 2.0), f"{where}.tolerance_c", PosePlanError, positive=True)
    return ChamberPlan(tuple(out), soak, tol)
