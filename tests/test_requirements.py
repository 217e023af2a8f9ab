"""The dependencies' floors (sfm_ttr_ros/requirements.py): stated once, repeated identically by
setup.py, requirements.txt and package.xml, and checked at start-up (a too-old pycolmap is one
clear error, not a stream of failed windows)."""

from __future__ import annotations

import os
import re
import runpy
import subprocess
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from sfm_ttr_ros import requirements as req
from sfm_ttr_ros.core.errors import InputError

REPO = Path(__file__).resolve().parents[1]


def fake_pycolmap(version: str, without: tuple[str, ...] = (),
                  api: tuple[str, ...] = req.PYCOLMAP_API) -> types.SimpleNamespace:
    """A module-like object with every name the code calls (as dotted attributes), less
    ``without``."""
    mod = types.SimpleNamespace(__version__=version)
    for dotted in api:
        if dotted in without:
            continue
        obj = mod
        parts = dotted.split(".")
        for part in parts[:-1]:
            if not hasattr(obj, part):
                setattr(obj, part, types.SimpleNamespace())
            obj = getattr(obj, part)
        setattr(obj, parts[-1], object())
    return mod


def test_setup_requirements_txt_and_package_xml_state_the_same_floors(monkeypatch):
    import setuptools

    captured = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: captured.update(kw))
    monkeypatch.chdir(REPO)
    runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    install = captured["install_requires"]
    for name in req.FLOORS:
        assert req.requirement(name) in install, (name, install)
    lines = {ln.strip() for ln in (REPO / "requirements.txt").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")}
    assert lines == {req.requirement(n) for n in ("pycolmap", "rosbags", "cmeel-mimalloc")}
    root = ET.parse(REPO / "package.xml").getroot()
    versions = {d.text: d.get("version_gte") for d in root.iter("exec_depend")}
    assert versions["python3-torch"] == req.FLOORS["torch"][0]
    assert all(v is None for k, v in versions.items() if k != "python3-torch")
    # the pip-only floors are named in package.xml's comment, as stated
    comment = (REPO / "package.xml").read_text()
    for name in ("pycolmap", "rosbags", "cmeel-mimalloc"):
        assert re.search(rf"{re.escape(name)} \(>= {re.escape(req.FLOORS[name][0])}\)", comment)


def test_versions_compare_by_their_numbers():
    assert req.version_tuple("2.13.0+cpu") == (2, 13, 0)
    assert req.version_tuple("4.3.0.dev1") == (4, 3, 0)
    assert req.version_tuple("unknown") == ()
    assert req.too_old("4.1.1", "4.2.0") and req.too_old("4.1.99", "4.2")
    assert not req.too_old("4.2", "4.2.0") and not req.too_old("4.10.0", "4.2.0")
    assert req.too_old("?", "4.2.0")  # an unreadable version is not trusted


def test_a_too_old_pycolmap_or_one_missing_an_api_is_one_clear_error():
    req.check_pycolmap(fake_pycolmap("4.2.0"))
    req.check_pycolmap(fake_pycolmap("4.3.1"))
    with pytest.raises(InputError, match=r"pycolmap 4\.1\.1 is too old: SfM needs "
                                         r"pycolmap>=4\.2\.0,<5 \(pycolmap\.CancellationToken"):
        req.check_pycolmap(fake_pycolmap("4.1.1"))
    with pytest.raises(InputError, match=r"pycolmap 4\.0\.4 is too old"):
        req.check_pycolmap(fake_pycolmap("4.0.4", without=("CancellationToken",)))
    with pytest.raises(InputError, match=r"pycolmap 4\.2\.5 lacks CancellationToken, "
                                         r"Device\.cpu, which SfM calls"):
        req.check_pycolmap(fake_pycolmap("4.2.5", without=("CancellationToken", "Device.cpu")))
    req.check_torch(fake_pycolmap("2.13.0+cpu", api=req.TORCH_API))
    with pytest.raises(InputError, match=r"torch 2\.1\.2 is too old.*NumPy 2"):
        req.check_torch(types.SimpleNamespace(__version__="2.1.2"))
    with pytest.raises(InputError, match=r"torch 2\.4\.0 lacks cuda\.graph, which the CUDA"):
        req.check_torch(fake_pycolmap("2.4.0", without=("cuda.graph",), api=req.TORCH_API))
    req.check_sfm_dependencies()  # the installed ones pass


def test_the_torch_api_of_the_cuda_path_is_listed_and_installed():
    """Every ``torch.cuda.X`` the CUDA path's modules name is in TORCH_API (so the check at
    start-up covers it), and the installed torch has them all; the one name newer than the
    floor (increment_version) is guarded by a fallback the floor has."""
    import torch

    assert not req._missing(torch, req.TORCH_API)
    used = set()
    for rel in ("core/refinement/graph_step.py", "core/refinement/graph_cache.py",
                "core/stream/serving.py"):
        text = (REPO / "sfm_ttr_ros" / rel).read_text()
        used |= {f"cuda.{n}" for n in re.findall(r"torch\.cuda\.([A-Za-z_]\w*)", text)}
        used |= {f"optim.{n}" for n in re.findall(r"torch\.optim\.([A-Za-z_]\w*)", text)}
        if "increment_version" in text:
            assert "_increment_version" in text  # the guarded fallback
    assert used <= set(req.TORCH_API), used - set(req.TORCH_API)


def test_the_installed_pycolmap_has_every_name_the_code_calls():
    import pycolmap

    assert not req._missing(pycolmap, req.PYCOLMAP_API)
    # and the list is complete: every pycolmap.X the package's code names is in it
    used = set()
    for path in (REPO / "sfm_ttr_ros").rglob("*.py"):
        used |= set(re.findall(r"pycolmap\.([A-Za-z_][A-Za-z_0-9]*)", path.read_text()))
    used -= {"libs", "__version__"}  # a folder in the wheel's comments; the version itself
    assert used <= {n.split(".")[0] for n in req.PYCOLMAP_API}, used


def test_the_cli_refuses_an_old_pycolmap_with_one_line(tmp_path):
    (tmp_path / "pycolmap.py").write_text('__version__ = "4.1.1"\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)])}
    out = subprocess.run([sys.executable, "-m", "sfm_ttr_ros.tools.cli", "run", "--images",
                          str(tmp_path / "none"), "--out", str(tmp_path / "out")],
                         env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sfm-ttr: error: pycolmap 4.1.1 is too old")
    assert not (tmp_path / "out").exists()
