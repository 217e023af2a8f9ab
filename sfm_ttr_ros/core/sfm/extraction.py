"""SfM's features and matches of a window (Sec. 3.1), by one of two back ends
(``sfm.features``):

* ``colmap``: pycolmap's SIFT and sequential matcher on the CPU (the reference);
* ``torch``: the weight-free torch SIFT of :mod:`.features.sift_torch` and mutual nearest
  neighbours with the ratio test, written into the same COLMAP database
  (:class:`~sfm_ttr_ros.core.sfm.features.database.TorchFeatureDatabase`), each pair verified
  by pycolmap.

Both write into the workspace's database (:mod:`.workspace`): a frame is extracted once and
sequential pairs matched in stream order, so overlapping windows only pay for new frames.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2

from sfm_ttr_ros.core.frames import Frame, Intrinsics
from sfm_ttr_ros.core.sfm.names import image_name
from sfm_ttr_ros.core.sfm.sfm_config import SfmConfig
from sfm_ttr_ros.core.sfm.workspace import SfmWorkspace


class FeatureMatcher:
    """Extraction and matching into one workspace's database; the torch back end's database
    writer lives as long as the database (:meth:`reset`)."""

    def __init__(self, workspace: SfmWorkspace, device: str | None = None):
        self.workspace = workspace
        # torch device of sfm.features "torch" (None: the GPU when torch sees one, else CPU)
        self.device = device
        self.torch_db = None  # TorchFeatureDatabase of this generation (sfm.features "torch")

    def reset(self) -> None:
        """The workspace started a new database."""
        self.torch_db = None

    def extract(self, config: SfmConfig, frames: Sequence[Frame], intr: Intrinsics,
                token) -> None:
        """Features of ``frames`` (none yet in the database) with the known PINHOLE intrinsics
        (one camera for the stream); the images are deleted once their keypoints are in."""
        import pycolmap

        if not frames:
            return
        ws = self.workspace
        ws.image_dir.mkdir(parents=True, exist_ok=True)
        for f in frames:
            cv2.imwrite(str(ws.image_dir / image_name(f.name)),
                        cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_PNG_COMPRESSION, 1])
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        # COLMAP puts pixel centres at +0.5; our intrinsics use OpenCV's integer centres.
        reader.camera_params = f"{intr.fx},{intr.fy},{intr.cx + 0.5},{intr.cy + 0.5}"
        if ws.camera_id is not None:
            reader.existing_camera_id = ws.camera_id
        if config.features == "torch":
            self._extract_torch(config, frames, reader)
        else:
            self._extract_colmap(config, frames, reader, token)
        for f in frames:
            (ws.image_dir / image_name(f.name)).unlink(missing_ok=True)  # keypoints suffice now
        with pycolmap.Database.open(ws.database_path) as db:
            if ws.camera_id is None:
                ws.camera_id = int(db.read_all_cameras()[0].camera_id)
        ws.names.extend(f.name for f in frames)

    def match(self, config: SfmConfig, token, check: Callable[[], None]) -> None:
        """Sequential matching of the database's frames in stream order (each with the next
        ``overlap``); ``check`` raises when the reconstruction is cancelled."""
        import pycolmap

        if config.features == "torch":
            # sequential matching in stream order, each pair verified by pycolmap
            self._torch_features(config).match(
                [image_name(n) for n in self.workspace.names], config.overlap, config.num_threads,
                token, check=check)
            return
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = config.num_threads
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.overlap
        pairing.quadratic_overlap = False
        pairing.loop_detection = False  # would download a vocabulary tree and abort offline
        pycolmap.match_sequential(self.workspace.database_path, matching_options=matching,
                                  pairing_options=pairing, device=pycolmap.Device.cpu,
                                  cancellation_token=token)

    def torch_timings(self, timings: dict[str, float], stage: str, ran) -> None:
        """The torch features' steps inside a stage (e.g. ``extract.detect_describe``,
        ``match.verify``), when sfm.features is "torch" and the stage ran."""
        if self.torch_db is not None and ran:
            timings.update((f"{stage}.{k}", v) for k, v in self.torch_db.timings.items())

    def _torch_features(self, config: SfmConfig):
        from sfm_ttr_ros.core.sfm.features.database import TorchFeatureDatabase
        from sfm_ttr_ros.core.sfm.features.sift_torch import TorchSiftConfig

        if self.torch_db is None:
            sift = TorchSiftConfig(first_octave=config.first_octave,
                                   max_num_features=config.max_num_features)
            self.torch_db = TorchFeatureDatabase(self.workspace.database_path, self.device,
                                                 sift, keep=config.overlap + 2)
        return self.torch_db

    def _extract_torch(self, config: SfmConfig, frames: Sequence[Frame], reader) -> None:
        """sfm.features "torch": images imported by pycolmap (camera, rig, frame), then torch
        SIFT keypoints and descriptors written into the database (core/sfm/features/)."""
        import pycolmap

        ws = self.workspace
        with pycolmap.Database.open(ws.database_path):
            pass  # import_images needs the database file to exist
        pycolmap.import_images(ws.database_path, ws.image_dir,
                               camera_mode=pycolmap.CameraMode.SINGLE,
                               image_names=[image_name(f.name) for f in frames], options=reader)
        self._torch_features(config).extract([(image_name(f.name), f.image) for f in frames],
                                             config.max_image_size)

    def _extract_colmap(self, config: SfmConfig, frames: Sequence[Frame], reader,
                        token) -> None:
        import pycolmap

        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = config.num_threads
        ext.max_image_size = config.max_image_size if config.max_image_size > 0 else -1
        ext.sift.max_num_features = config.max_num_features
        ext.sift.first_octave = config.first_octave
        pycolmap.extract_features(
            self.workspace.database_path, self.workspace.image_dir,
            image_names=[image_name(f.name) for f in frames],
            camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
            extraction_options=ext, device=pycolmap.Device.cpu, cancellation_token=token,
        )
