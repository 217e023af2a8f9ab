"""A pycolmap ``DatabaseCache`` built from the front end's Python-held features, and the
incremental mapper's steps that continue a reconstruction over it.

A cache cannot be refreshed once its correspondence graph is finalised, so every mapping step
gets a new cache (and a new ``IncrementalMapper``) over exactly the frames it may use: no SQLite,
no pairs outside those frames.
The continuation is COLMAP's own per-image loop (``IncrementalPipeline::ReconstructSubModel``):
next image by the mapper's ranking, 2D-3D registration, triangulation, iterative local bundle
adjustment; no global adjustment and no normalisation, so the map keeps its coordinates and its
scale from window to window.
"""

from __future__ import annotations

from collections.abc import Iterable

from sfm_ttr_ros.core.sfm.frontend import CAMERA_ID, StreamFrontend
from sfm_ttr_ros.core.sfm.names import image_name


def build_cache(frontend: StreamFrontend, names: Iterable[str]):
    """A finalised ``DatabaseCache`` of the held frames among ``names`` and their verified
    pairs (those with at least ``MIN_PAIR_INLIERS`` inliers)."""
    import pycolmap

    cache = pycolmap.DatabaseCache()
    cache.add_camera(frontend.camera)
    rig = pycolmap.Rig()
    rig.rig_id = CAMERA_ID
    sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, CAMERA_ID)
    rig.add_ref_sensor(sensor)
    cache.add_rig(rig)
    ids = frontend.ids(names)
    for name, iid in ids.items():
        frame = pycolmap.Frame()
        frame.frame_id = iid
        frame.rig_id = CAMERA_ID
        frame.add_data_id(pycolmap.data_t(sensor, iid))
        cache.add_frame(frame)
        image = pycolmap.Image(name=image_name(name), keypoints=frontend.features[name].xy,
                               camera_id=CAMERA_ID, image_id=iid)
        image.frame_id = iid
        cache.add_image(image)
    held = set(ids.values())
    graph = cache.correspondence_graph
    for (i, j), tvg in frontend.pairs.items():
        if i in held and j in held:
            graph.add_two_view_geometry(i, j, tvg)
    graph.finalize()
    return cache


def continue_reconstruction(rec, cache, options) -> list[int]:
    """Register every frame of ``cache`` that ``rec`` can take, in the mapper's order, each
    triangulated and locally adjusted (COLMAP's incremental loop); ``rec`` must hold at least
    one registered frame, all of them in ``cache``. Modifies ``rec`` in place; returns the
    newly registered image ids. COLMAP's random generator (per thread: it would carry on from
    whatever ran before in this thread) is seeded with ``options.random_seed`` first, so a
    continuation is the same in any process."""
    import pycolmap

    pycolmap.set_random_seed(int(options.random_seed))
    mopts = options.get_mapper()
    tri = options.get_triangulation()
    local_ba = options.get_local_bundle_adjustment()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    added: list[int] = []
    fallback = options.structure_less_registration_fallback
    try:
        while (iid := _register_next(mapper, mopts, fallback)) is not None:
            added.append(iid)
            for data in rec.image(iid).frame.image_ids:
                mapper.triangulate_image(tri, data.id)
            mapper.iterative_local_refinement(
                options.ba_local_max_refinements, options.ba_local_max_refinement_change,
                mopts, local_ba, tri, iid)
    finally:
        mapper.end_reconstruction(False)  # drops the frames left unregistered
    return added


def _register_next(mapper, mopts, structure_less_fallback: bool) -> int | None:
    """The first candidate the mapper ranks that registers from 2D-3D matches; failing all,
    the first that registers structure-less (when the fallback is on); else None."""
    for structure_less in (False, True)[:1 + bool(structure_less_fallback)]:
        register = (mapper.register_next_structure_less_image if structure_less
                    else mapper.register_next_image)
        for iid in mapper.find_next_images(mopts, structure_less=structure_less):
            if register(mopts, iid):
                return int(iid)
    return None
