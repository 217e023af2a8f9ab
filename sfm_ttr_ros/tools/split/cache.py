"""The resume store of a split's output folder: ``OUT/sequences/<id>/`` holds a sequence's
files and, written last, ``sequence.json`` with its key and row. A sequence whose
``sequence.json`` has the key of the present run is not computed again (unless
``--overwrite``); an interrupted split so continues where it stopped.

The key (:func:`sequence_key`) is a hash of the sequence's line (kind, path, options, frames),
the command and its options, the parameter values (the threads excepted: they change the
speed, not the method), the fingerprint of the model files the values name (size and
modification time) and of the package's code (:func:`code_fingerprint`: every Python source of
``sfm_ttr_ros`` and ``msg_adapters`` and the embedded weights). Data changed in place under the
same paths is not detected: ``--overwrite`` recomputes.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

from sfm_ttr_ros.tools.split.spec import SequenceSpec
from sfm_ttr_ros.tools.split.task import SequenceOutcome, SplitJob

MARKER = "sequence.json"
SEQUENCES = "sequences"
FAILED = "failed"
#: Parameters that set how many threads run, not what is computed: not part of the key.
THREAD_PARAMS = ("torch_num_threads", "sfm.num_threads", "worker_threads")
#: Parameters naming a model file: their size and modification time are part of the key.
FILE_PARAMS = ("encoder_path", "decoder_path", "model_path", "load_weights_path")


@functools.cache
def code_fingerprint() -> str:
    """sha256 of the package's Python sources and embedded weights (path and content)."""
    import msg_adapters
    import sfm_ttr_ros

    h = hashlib.sha256()
    for pkg in (sfm_ttr_ros, msg_adapters):
        root = Path(pkg.__file__).resolve().parent
        for p in sorted(root.rglob("*")):
            if p.suffix in (".py", ".pth") and p.is_file() and "__pycache__" not in p.parts:
                h.update(f"{pkg.__name__}/{p.relative_to(root)}\0".encode())
                h.update(p.read_bytes())
    return h.hexdigest()


def _file_stamp(path: str) -> list[Any] | None:
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def sequence_key(spec: SequenceSpec, job: SplitJob) -> str:
    """The resume key of ``spec`` under ``job`` (module docstring)."""
    values = {k: v for k, v in job.values.items() if k not in THREAD_PARAMS}
    files = {k: _file_stamp(str(values[k])) for k in FILE_PARAMS if values.get(k)}
    doc = {"sequence": spec.identity(), "command": job.command, "options": job.options,
           "values": values, "files": files, "code": code_fingerprint()}
    text = json.dumps(doc, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def sequence_dir(out: Path, spec_id: str) -> Path:
    return Path(out) / SEQUENCES / spec_id


def load_done(out: Path, spec: SequenceSpec, key: str) -> dict[str, Any] | None:
    """The stored record of ``spec`` when it was computed with ``key``, else None."""
    path = sequence_dir(out, spec.id) / MARKER
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if record.get("key") != key or record.get("status") != "done":
        return None
    return record


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
    tmp.write_text(json.dumps(doc, indent=2, default=str) + "\n")
    os.replace(tmp, path)


def store(out: Path, spec: SequenceSpec, outcome: SequenceOutcome, key: str,
          attempts: int) -> dict[str, Any]:
    """Write ``outcome`` under ``out``; returns its record. A done sequence's files go to a
    scratch folder first, its marker last, then the folder replaces the old one: an interrupt
    never leaves a marker over missing files. A failed one is written to
    ``OUT/failed/<id>.json`` (its reason, and the traceback of an error of the method)."""
    out = Path(out)
    record = {"id": spec.id, "key": key, "status": outcome.status, "reason": outcome.reason,
              "reason_key": outcome.reason_key,
              "row": outcome.row, "seconds": outcome.seconds, "host": outcome.host,
              "attempts": attempts, "lines": list(spec.lines), "source": spec.describe(),
              "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    failed = out / FAILED / f"{spec.id}.json"
    if outcome.status != "done":
        failed.parent.mkdir(parents=True, exist_ok=True)
        _write_json(failed, {**record, "detail": outcome.detail})
        return record
    final = sequence_dir(out, spec.id)
    scratch = final.with_name(f".{spec.id}.{uuid.uuid4().hex}")
    scratch.mkdir(parents=True)
    for rel, data in outcome.files.items():
        target = scratch / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    _write_json(scratch / MARKER, record)
    if final.exists():
        shutil.rmtree(final)
    os.replace(scratch, final)
    failed.unlink(missing_ok=True)
    return record
