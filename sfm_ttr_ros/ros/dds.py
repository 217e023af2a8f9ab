"""The DDS profile the ``refiner`` gives its own process: Fast DDS tuned for large images.

Fast DDS (rmw_fastrtps_cpp, Jazzy's default) sends same-host samples through a shared-memory
segment of 512 KB by default, a quarter of one 1242x375 depth image. On a loaded machine the
fragments that do not fit are dropped; a reliable reader then holds every later sample back
until the writer's next heartbeat (~3 s) repairs the hole, and a burst on ``~/depth_refined/image``
(up to ``max_pending`` images at once after an overload) can lose samples outright.
``params/fastdds_large_images.xml`` gives the writer a 64 MB segment and a 100 ms heartbeat
(the measured latencies with and without it: BENCHMARKS.md "Soak").

The segment and the heartbeat belong to the WRITER, so the node's own profile fixes its outputs
for every subscriber. :func:`apply_profile` points Fast DDS at it before ``rclpy.init`` unless
the user chose otherwise: another RMW, a profile of their own (``FASTRTPS_DEFAULT_PROFILES_FILE``
/ ``FASTDDS_DEFAULT_PROFILES_FILE``, a ``DEFAULT_FASTDDS_PROFILES.xml`` in the working folder,
``SKIP_DEFAULT_XML_FILE``), or ``SFM_TTR_DDS_PROFILE=none``. ``SFM_TTR_DDS_PROFILE=<path>``
picks another profile file.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from pathlib import Path

from sfm_ttr_ros.ros.share import find_share_file

PROFILE_NAME = "fastdds_large_images.xml"
#: The variables through which a user has already told Fast DDS what to load.
USER_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
                     "SKIP_DEFAULT_XML_FILE")
OPT_VAR = "SFM_TTR_DDS_PROFILE"


def apply_profile(environ: MutableMapping[str, str] | None = None,
                  cwd: str | Path | None = None) -> str:
    """Set ``FASTRTPS_DEFAULT_PROFILES_FILE`` to the node's profile in ``environ`` (the process
    environment) where nobody chose otherwise (module docstring); what was done, one line."""
    env = os.environ if environ is None else environ
    choice = env.get(OPT_VAR, "").strip()
    rmw = env.get("RMW_IMPLEMENTATION", "")
    if choice.lower() == "none":
        return f"DDS profile: none ({OPT_VAR}=none)"
    if rmw and not rmw.startswith("rmw_fastrtps"):
        return f"DDS profile: none ({rmw} is not Fast DDS)"
    chosen = [v for v in USER_PROFILE_VARS if env.get(v)]
    if chosen:
        return f"DDS profile: the user's ({chosen[0]} is set)"
    if (Path(cwd or os.getcwd()) / "DEFAULT_FASTDDS_PROFILES.xml").is_file():
        return "DDS profile: the user's (DEFAULT_FASTDDS_PROFILES.xml in the working folder)"
    path = Path(choice) if choice else find_share_file("params", PROFILE_NAME)
    if path is None or not path.is_file():
        return f"DDS profile: none ({choice or PROFILE_NAME} not found)"
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(path)
    return f"DDS profile: {path} (large images; {OPT_VAR}=none turns it off)"
