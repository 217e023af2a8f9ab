"""The stream's camera path: the one :class:`~sfm_ttr_ros.core.camera_path.CameraPath` of a
stream, extended where windows finish, in the metres of the stream's depth.

:meth:`StreamPath.window` takes a finished window's frames (their stamps), its result (the
reconstruction's poses) and the factor its depth outputs were made with
(:attr:`~.records.FrameOutput.metres_per_unit`): the path is in metres exactly when that depth
is (core/camera_path.py, "Units"). What it returns, the poses new to the path in stamp order
with their units, is what the window reports (:attr:`~.records.WindowStats.path_poses`) and
what the node publishes (``~/odom``) and the benchmark measures (``path``). The window runner
(:class:`~.windows.WindowRunner`) keeps one; a caller that runs windows without the stream
keeps its own.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from sfm_ttr_ros.core.camera_path import CameraPath, result_poses
from sfm_ttr_ros.core.frames import Frame
from sfm_ttr_ros.core.stream.frame_queue import RELEASED_IMAGE
from sfm_ttr_ros.core.stream.records import FramePose
from sfm_ttr_ros.core.window_io import WindowResult


class StreamPath:
    """The camera's path of one stream (module docstring)."""

    def __init__(self, max_poses: int = 100_000) -> None:
        self.path = CameraPath(max_poses)

    def window(self, frames: Sequence[Frame], result: WindowResult,
               metres_per_unit: float | None) -> list[FramePose]:
        """Chain the window over ``frames`` (``result`` its core result) onto the path, in the
        metres of depth outputs made with ``metres_per_unit`` (None: not in metres); the poses
        new to the path, in stamp order. Stamps: the window's frames', and for the frames a
        fresh map was mapped with (``SfmResult.anchors``, before the window) the path's own."""
        by_name = {f.name: f for f in frames}
        stamps = {f.name: f.stamp for f in frames}
        if result.sfm is not None:
            stamps.update((n, self.path.poses[n].stamp) for n in result.sfm.anchors
                          if n not in stamps and n in self.path.poses)
        poses = result_poses(result, stamps, metres_per_unit)
        if poses is None:
            return []
        return [FramePose(dataclasses.replace(by_name[p.name], image=RELEASED_IMAGE), p,
                          self.path.units) for p in self.path.add(poses)]

    def summary(self) -> dict[str, object]:
        """The path's units, poses, windows by how they were chained, breaks."""
        return self.path.summary()
