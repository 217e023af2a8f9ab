"""The sections of a ROS 2 parameter file and which of them apply to a node, as rcl decides
(ROS 2 design "ROS 2 node parameters", YAML file format; rcl's ``wildcard_to_regex``):

* a section is a node name pattern: ``/ns/refiner``, ``refiner`` (= ``/refiner``: a name without
  a leading ``/`` is read from the root namespace), with the wildcards ``/**`` (zero or more
  namespace tokens or names) and ``/*`` (exactly one); ``/**`` alone applies to every node,
  ``/**/refiner`` to every ``refiner``, ``/cam1/*`` to every node in ``/cam1``;
* a pattern matches the node's fully qualified name as a whole (``/cam1/refiner``);
* sections that name the same pattern are one (the first one's place), and the sections that
  match are applied in the file's order: a later section overrides an earlier one key by key.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from sfm_ttr_ros.core.errors import InputError

_TOKEN = r"[A-Za-z0-9_]+"


def full_node_name(node_name: str, namespace: str = "") -> str:
    """The node's fully qualified name: ``/<namespace>/<node_name>`` (``/refiner`` in the root
    namespace; a namespace without a leading ``/`` is read from the root, as ``__ns`` is)."""
    ns = str(namespace).strip().strip("/")
    return f"/{ns}/{node_name}" if ns else f"/{node_name}"


def section_name(section: str) -> str:
    """A section's node name pattern with its leading ``/`` (``refiner`` → ``/refiner``)."""
    s = str(section).strip()
    return s if s.startswith("/") else f"/{s}"


def is_wildcard_section(section: str) -> bool:
    """True for a section that may apply to several nodes (a pattern with ``*``)."""
    return "*" in str(section)


def section_pattern(section: str) -> re.Pattern:
    """rcl's reading of a section's name: each ``/**`` zero or more ``/token``, each ``/*``
    one, any other token itself."""
    parts = []
    for token in section_name(section).split("/")[1:]:
        if token == "**":
            parts.append(f"(/{_TOKEN})*")
        elif token == "*":
            parts.append(f"/{_TOKEN}")
        else:
            parts.append("/" + re.escape(token))
    return re.compile("".join(parts))


def section_matches(section: str, fqn: str) -> bool:
    """True when the parameter file's ``section`` applies to the node named ``fqn``
    (``/cam1/refiner``)."""
    return section_pattern(section).fullmatch(fqn) is not None


def _flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def parameter_sections(path: Path) -> list[tuple[str, dict[str, Any]]]:
    """Each section of the ROS 2 parameter file at ``path`` that has ``ros__parameters``: its
    node name pattern (with its leading ``/``: ``/**``, ``/refiner``, ``/ns/refiner``, ...) and
    its parameters, nested mappings flattened with dots, in the file's order (sections that
    name the same pattern merged at the first one's place, the later's keys winning)."""
    import yaml

    if not path.is_file():
        raise InputError(f"parameter file not found: {path}")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(f"cannot read parameter file {path}: {exc}") from exc
    if not isinstance(doc, Mapping):
        raise InputError(f"{path}: expected a mapping of node names to ros__parameters")
    sections: dict[str, dict[str, Any]] = {}
    for section, body in doc.items():
        s = section_name(section)
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            continue
        params = body["ros__parameters"]
        if not isinstance(params, Mapping):
            raise InputError(f"{path}: ros__parameters of {s!r} is not a mapping")
        sections.setdefault(s, {}).update(_flatten(params))
    return list(sections.items())


def no_section_message(path: str | Path, fqn: str, sections: list[str]) -> str:
    """What to say of a parameter file none of whose ``sections`` applies to node ``fqn``."""
    have = ", ".join(sections) if sections else "none with ros__parameters"
    return (f"{path}: no section applies to node {fqn} (its sections: {have}), so none of its "
            f"values does; name the section {fqn!r}, or '/**' for any namespace")


def params_file_arguments(args: Sequence[str]) -> list[str]:
    """The files of the ``--params-file FILE`` among the ROS arguments of ``args`` (each
    ``--ros-args`` up to its ``--`` or the end), in order."""
    files, in_ros = [], False
    args = list(args)
    for i, arg in enumerate(args):
        if arg == "--ros-args":
            in_ros = True
        elif in_ros and arg == "--":
            in_ros = False
        elif in_ros and arg == "--params-file" and i + 1 < len(args):
            files.append(args[i + 1])
    return files


def unapplied_files(args: Sequence[str], fqn: str) -> list[str]:
    """One message for each ``--params-file`` of ``args`` none of whose sections applies to the
    node ``fqn``: rcl starts the node without its values and says nothing. A file rcl could
    not read is rcl's to refuse: not reported here."""
    messages = []
    for file in params_file_arguments(args):
        try:
            sections = [s for s, _ in parameter_sections(Path(file))]
        except InputError:
            continue
        if not any(section_matches(s, fqn) for s in sections):
            messages.append(no_section_message(file, fqn, sections))
    return messages
