"""The split file: which sequences one ``--split FILE`` command runs.

One sequence per line; ``#`` starts a comment; blank lines are skipped. A line is either a
kind, a path and ``key=value`` options::

    kitti  2011_09_26_drive_0002_sync [raw=DIR] [gt=DIR] [start=N] [frames=N] [name=ID]
    images DIR K=FILE [gt=DIR] [gt_scale=256] [start=N] [frames=N] [name=ID]
    bag    DIR [image=TOPIC] [camera_info=TOPIC] [gt=TOPIC] [start=N] [frames=N] [name=ID]

or a line of the KITTI Eigen split file as published (``eigen_test_files.txt``)::

    2011_09_26/2011_09_26_drive_0002_sync 0000000069 l

Eigen lines name frames to evaluate; the lines of one drive (and side, ``l`` = camera 02,
``r`` = camera 03) make one sequence, run over the drive's frames from ``context`` frames
before its first listed frame to ``context`` frames after its last (clamped to the drive), and
evaluated on the listed frames only (:mod:`.sources`). ``kitti`` and Eigen lines read the
``--kitti-raw`` / ``--kitti-gt`` roots unless ``raw=`` / ``gt=`` say otherwise. Relative paths
are relative to the split file's folder. Every sequence has an id (``name=``, else the drive,
the folder's or the bag's name; ``_right`` appended for an Eigen ``r`` side): its results go to
``OUT/sequences/<id>/``; two sequences with one id are an error.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.errors import InputError

KINDS = ("kitti", "images", "bag")
#: Options each kind accepts (``name``, ``start`` and ``frames`` are common to all).
OPTIONS = {
    "kitti": ("raw", "gt"),
    "images": ("K", "gt", "gt_scale"),
    "bag": ("image", "camera_info", "gt"),
}
COMMON = ("name", "start", "frames")
#: Options holding a path (resolved against the split file's folder).
PATH_OPTIONS = {"kitti": ("raw", "gt"), "images": ("K", "gt"), "bag": ()}
_EIGEN_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})/(\1_drive_\d{4}_sync)\s+(\d+)\s+([lr])$")
_ID_RE = re.compile(r"^[A-Za-z0-9._-]+$")
EIGEN_CAMERAS = {"l": "02", "r": "03"}


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence of a split: what to read (``kind``, ``path``, ``options``), the frames to
    run (``start``, ``frames``: 0 = to the end), for Eigen lines the frames to evaluate
    (``eval_frames``, frame names; None = every frame with ground truth) and the ``context``
    around them, and where it came from (``lines``)."""

    id: str
    kind: str
    path: str
    options: dict[str, str] = field(default_factory=dict)
    start: int = 0
    frames: int = 0
    camera: str = "02"
    eval_frames: tuple[str, ...] | None = None
    context: int = 0
    lines: tuple[int, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["eval_frames"] = None if self.eval_frames is None else list(self.eval_frames)
        d["lines"] = list(self.lines)
        return d

    def identity(self) -> dict[str, Any]:
        """What the results depend on (for the resume key): everything but the line numbers."""
        d = self.as_dict()
        d.pop("lines")
        return d

    def describe(self) -> str:
        if self.eval_frames is not None:
            return f"{self.path} ({len(self.eval_frames)} listed frames)"
        return f"{self.kind} {self.path}"


def _int_option(value: str, key: str, where: str) -> int:
    try:
        n = int(value)
    except ValueError:
        raise InputError(f"{where}: {key}= takes a whole number, got {value!r}") from None
    if n < 0:
        raise InputError(f"{where}: {key}= must be >= 0, got {n}")
    return n


def _resolve(base: Path, text: str) -> str:
    p = Path(text).expanduser()
    return str(p if p.is_absolute() else (base / p))


def _parse_kind_line(tokens: list[str], where: str, base: Path, roots: dict[str, str | None]
                     ) -> SequenceSpec:
    kind = tokens[0]
    if len(tokens) < 2 or "=" in tokens[1]:
        raise InputError(f"{where}: '{kind}' needs a path after it")
    path = tokens[1]
    opts: dict[str, str] = {}
    for tok in tokens[2:]:
        key, sep, value = tok.partition("=")
        if not sep or not value:
            raise InputError(f"{where}: expected key=value, got {tok!r}")
        if key not in OPTIONS[kind] + COMMON:
            raise InputError(f"{where}: unknown option {key!r} for {kind} (known: "
                             f"{', '.join(OPTIONS[kind] + COMMON)})")
        if key in opts:
            raise InputError(f"{where}: {key}= given twice")
        opts[key] = value
    for key in PATH_OPTIONS[kind]:
        if key in opts:
            opts[key] = _resolve(base, opts[key])
    start = _int_option(opts.pop("start", "0"), "start", where)
    frames = _int_option(opts.pop("frames", "0"), "frames", where)
    name = opts.pop("name", None)
    if kind == "kitti":
        for key, root in (("raw", roots.get("raw")), ("gt", roots.get("gt"))):
            if key not in opts and root:
                opts[key] = str(root)
        if "raw" not in opts:
            raise InputError(f"{where}: a kitti line needs raw=DIR or --kitti-raw")
        default_id = path
    else:
        path = _resolve(base, path)
        if kind == "images" and "K" not in opts:
            raise InputError(f"{where}: an images line needs K=FILE (3x3 or fx fy cx cy)")
        default_id = Path(path).name
    sid = name or default_id
    return SequenceSpec(id=sid, kind=kind, path=path, options=opts, start=start, frames=frames,
                        lines=(int(where.rsplit(":", 1)[1]),))


def read_split(path: str | Path, kitti_raw: str | None = None, kitti_gt: str | None = None,
               context: int = 10) -> list[SequenceSpec]:
    """The sequences of the split file ``path`` in file order (an Eigen drive where its first
    line is). :class:`InputError` for an unreadable file, a bad line, no sequence or two
    sequences with one id."""
    path = Path(path)
    if context < 0:
        raise InputError(f"the Eigen context must be >= 0 frames, got {context}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the split file {path}: {exc}") from exc
    base = path.resolve().parent
    roots = {"raw": _resolve(base, kitti_raw) if kitti_raw else None,
             "gt": _resolve(base, kitti_gt) if kitti_gt else None}
    specs: list[SequenceSpec | None] = []
    eigen: dict[tuple[str, str], dict[str, Any]] = {}
    for lineno, raw_line in enumerate(text.splitlines(), 1):
        line = raw_line.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path}:{lineno}"
        m = _EIGEN_RE.match(line)
        if m:
            if not roots["raw"]:
                raise InputError(f"{where}: an Eigen-split line needs --kitti-raw (and "
                                 "--kitti-gt for the improved ground truth)")
            drive, frame, side = m.group(2), m.group(3), m.group(4)
            entry = eigen.get((drive, side))
            if entry is None:
                entry = eigen[(drive, side)] = {"frames": [], "lines": [], "slot": len(specs)}
                specs.append(None)  # filled below, keeping the file's order
            if frame in entry["frames"]:
                raise InputError(f"{where}: frame {frame} of {drive} listed twice")
            entry["frames"].append(frame)
            entry["lines"].append(lineno)
            continue
        tokens = line.split()
        if tokens[0] not in KINDS:
            raise InputError(f"{where}: expected a line '<{'|'.join(KINDS)}> PATH [key=value "
                             f"...]' or an Eigen-split line '<date>/<drive> <frame> l|r', got "
                             f"{line!r}")
        specs.append(_parse_kind_line(tokens, where, base, roots))
    for (drive, side), entry in eigen.items():
        opts = {"raw": str(roots["raw"])}
        if roots["gt"]:
            opts["gt"] = str(roots["gt"])
        specs[entry["slot"]] = SequenceSpec(
            id=drive + ("_right" if side == "r" else ""), kind="kitti", path=drive,
            options=opts, camera=EIGEN_CAMERAS[side], eval_frames=tuple(entry["frames"]),
            context=context, lines=tuple(entry["lines"]))
    out = [s for s in specs if s is not None]
    if not out:
        raise InputError(f"the split file {path} lists no sequence")
    seen: dict[str, SequenceSpec] = {}
    for s in out:
        if not _ID_RE.match(s.id):
            raise InputError(f"{path}:{s.lines[0]}: sequence id {s.id!r} may hold only letters, "
                             "digits, '.', '_' and '-' (give name=ID)")
        if s.id in seen:
            raise InputError(f"{path}:{s.lines[0]}: sequence id {s.id!r} already used on line "
                             f"{seen[s.id].lines[0]} (give name=ID)")
        seen[s.id] = s
    return out
