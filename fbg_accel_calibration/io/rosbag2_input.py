"""rosbag2 bag directories as inputs of the offline tools (pure Python + PyYAML, no rclpy).

``ros2 bag record -s mcap /ns/imu/raw ...`` writes a DIRECTORY: ``metadata.yaml`` (key
``rosbag2_bagfile_information``) and one or more ``.mcap`` files named in its ``relative_file_paths``,
in recording order (a split bag has several). :func:`bag_files` gives those files and the topics the
metadata lists (full names with a leading slash, e.g. ``/veh1/imu/raw``, and their ROS 2 types), so a
reader can choose the topics before opening any file. The files of one bag are ONE recording.

Also: :func:`offered_qos_yaml`, the ``offered_qos_profiles`` channel metadata string the MCAP ROS 2
profile requires and rosbag2's MCAP storage writes (a YAML list of QoS profiles, rosbag2 format 9
spelling: policy names in lower case, durations as ``sec``/``nsec``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from fbg_accel_driver.yaml_input import YamlFileError, read_yaml_file

METADATA_FILE = "metadata.yaml"
_MAX_METADATA_BYTES = 16 << 20


class BagInputError(ValueError):
    """A bag directory cannot be read as a recording (one line naming the directory/file and the field)."""


@dataclass
class BagInfo:
    """What ``metadata.yaml`` says about a bag: its data files in order and its topics (name -> type)."""

    path: Path
    files: list[Path]
    topics: dict[str, str]
    unlisted: list[Path] = field(default_factory=list)  # .mcap files in the directory that metadata.yaml omits
    repeated: list[str] = field(default_factory=list)  # relative_file_paths entries naming a file listed before

    def notes(self) -> list[str]:
        """Warning lines about the bag: its unlisted .mcap files, which are not read, and files listed twice, read
        once."""
        out = []
        if self.unlisted:
            names = ", ".join(p.name for p in self.unlisted)
            out.append(f"{self.path}: {names} not listed in {METADATA_FILE}'s relative_file_paths, not read (a recorder "
                       f"stopped before updating {METADATA_FILE}? `ros2 bag reindex {self.path}` rebuilds it from the "
                       "files)")
        if self.repeated:
            out.append(f"{self.path}: {METADATA_FILE}'s relative_file_paths lists {', '.join(self.repeated)} twice or "
                       "more; each file is read once")
        return out


def bag_files(path: str | Path) -> BagInfo:
    """Parse ``<path>/metadata.yaml``: the ``.mcap`` files of ``relative_file_paths`` (in that order,
    each must exist) and the topics of ``topics_with_message_count``. Raises :class:`BagInputError`."""
    path = Path(path)
    meta = path / METADATA_FILE
    if not os.path.lexists(meta):  # anything else at that name is said as what it is by read_yaml_file
        raise BagInputError(f"{path}: a directory without {METADATA_FILE}; give a rosbag2 bag directory "
                            "(ros2 bag record -s mcap ...) or an .mcap/.csv file")
    try:
        doc = read_yaml_file(meta, "rosbag2 metadata file", _MAX_METADATA_BYTES)
    except YamlFileError as exc:
        raise BagInputError(str(exc)) from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagInputError(f"{meta}: no 'rosbag2_bagfile_information' mapping; not a rosbag2 metadata file")
    storage = info.get("storage_identifier", "")
    if storage != "mcap":
        raise BagInputError(f"{meta}: storage_identifier is {storage!r}; only 'mcap' bags are read "
                            "(record with ros2 bag record -s mcap, or convert with ros2 bag convert)")
    mode = str(info.get("compression_mode") or "").strip()
    if mode and mode.lower() != "none":
        what = "each .mcap file is compressed whole" if mode.lower() == "file" else "each message is compressed"
        raise BagInputError(f"{meta}: compression_mode {mode!r} ({info.get('compression_format') or '?'}): {what}, "
                            "which is not read; convert it to an uncompressed MCAP bag with ros2 bag convert "
                            "(output options without compression_mode), or record with the MCAP storage's own chunk "
                            "compression (ros2 bag record -s mcap --storage-preset-profile zstd_fast)")
    rel = info.get("relative_file_paths")
    if not isinstance(rel, list) or not rel or not all(isinstance(r, str) and r for r in rel):
        raise BagInputError(f"{meta}: relative_file_paths must be a non-empty list of file names")
    files: list[Path] = []
    repeated: list[str] = []
    for name in rel:
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise BagInputError(f"{meta}: relative_file_paths entry {name!r} leaves the bag directory")
        candidate = path / name
        if not candidate.is_file() and (path / Path(name).name).is_file():
            candidate = path / Path(name).name  # older rosbag2 wrote the bag directory's name in front
        if not candidate.is_file():
            raise BagInputError(f"{meta}: relative_file_paths names {name!r}, which is not in {path}")
        if any(candidate.samefile(f) for f in files):
            repeated.append(name)
            continue
        files.append(candidate)
    topics: dict[str, str] = {}
    listed_topics = info.get("topics_with_message_count") or []
    if not isinstance(listed_topics, list):
        raise BagInputError(f"{meta}: topics_with_message_count must be a list, got {type(listed_topics).__name__}")
    for item in listed_topics:
        tm = item.get("topic_metadata") if isinstance(item, dict) else None
        if isinstance(tm, dict) and isinstance(tm.get("name"), str):
            topics[tm["name"]] = str(tm.get("type", "?"))
    listed = {f.resolve() for f in files}
    unlisted = sorted(p for p in path.iterdir() if p.suffix == ".mcap" and p.is_file() and p.resolve() not in listed)
    return BagInfo(path, files, topics, unlisted, repeated)


def offered_qos_yaml(reliable: bool = True, depth: int = 10, transient_local: bool = False) -> str:
    """``offered_qos_profiles`` channel metadata: a YAML list with one profile (keep_last ``depth``,
    reliable or best_effort, volatile or transient_local, automatic liveliness; deadline, lifespan and
    lease duration 0 s = the middleware default, i.e. unset)."""
    unset = {"sec": 0, "nsec": 0}
    profile = {"history": "keep_last", "depth": int(depth),
               "reliability": "reliable" if reliable else "best_effort",
               "durability": "transient_local" if transient_local else "volatile",
               "deadline": dict(unset), "lifespan": dict(unset), "liveliness": "automatic",
               "liveliness_lease_duration": dict(unset), "avoid_ros_namespace_conventions": False}
    return yaml.safe_dump([profile], sort_keys=False, default_flow_style=False).strip()
