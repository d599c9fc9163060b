"""The two mapping strategies of `run_sfm` (calibration/sfm.py): COLMAP's incremental mapper with the rig
applied afterwards, and a rig-structured refinement from the nominal poses; plus bundle-adjustment options and
reprojection errors."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lightstage.calibration.export import colmap_image_name
from lightstage.errors import LightstageError
from lightstage.ids import ViewId

if TYPE_CHECKING:
    from lightstage.calibration.sfm import SfmOptions


def image_name(view: ViewId) -> str:
    """The view's image name in the COLMAP database and model (the export's convention, one definition)."""
    return colmap_image_name(view.group, view.camera)


def incremental(db_path, image_dir, sparse_dir, views, cams_present, mapping, options, t_start):
    """COLMAP's incremental mapper without rig constraints, then the rig applied and bundle-adjusted."""
    import time

    import pycolmap

    recs = pycolmap.incremental_mapping(db_path, image_dir, sparse_dir, options=mapping)
    t_map = time.perf_counter() - t_start
    if not recs:
        raise LightstageError(
            f"SfM failed: no reconstruction from {len(views)} views (too few matches on the foreground?); "
            f"unregistered views: {view_list(sorted(views))}"
        )
    rec = max(recs.values(), key=lambda r: r.num_reg_images())

    # Pass 2 (COLMAP's documented two-pass rig workflow; its rig-aware incremental mapper stalled after two
    # frames on turntable data): derive the rig (mean sensor-from-reference poses over the groups) from the
    # unconstrained reconstruction, turn the images of a group into one rig frame, and bundle-adjust with the
    # rig constraint. The first camera is the reference sensor.
    reg_names = {rec.images[i].name for i in rec.reg_image_ids()}
    lost = [c for c in cams_present if not any(n.startswith(c + "/") for n in reg_names)]
    if lost:
        raise LightstageError(
            f"SfM failed: cameras {', '.join(lost)} have no registered view; unregistered views: "
            f"{view_list(sorted(v for v in views if image_name(v) not in reg_names))}"
        )
    if options.use_rig:
        rig_config = pycolmap.RigConfig()
        rig_cams = []
        for cid in cams_present:
            rc = pycolmap.RigConfigCamera()
            rc.image_prefix = f"{cid}/"
            rc.ref_sensor = cid == cams_present[0]
            rig_cams.append(rc)
        rig_config.cameras = rig_cams
        with pycolmap.Database.open(db_path) as db:
            pycolmap.apply_rig_config([rig_config], db, rec)

    if options.final_ba_iterations > 0:
        pycolmap.bundle_adjustment(
            rec, ba_options(options, robust=False, iterations=options.final_ba_iterations)
        )
    t_ba = time.perf_counter() - t_start - t_map

    return rec, recs, t_map, t_ba


def ba_options(options: SfmOptions, robust: bool, iterations: int):
    import pycolmap

    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = False
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.refine_sensor_from_rig = options.refine_rig
    ba.print_summary = options.verbose
    if robust:
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        ba.ceres.loss_function_scale = 1.0
    so = ba.ceres.solver_options
    so.max_num_iterations = iterations
    so.function_tolerance = 1e-12
    so.gradient_tolerance = 1e-12
    so.parameter_tolerance = 1e-12
    so.num_threads = options.num_threads
    return ba


def refine_from_initial(
    db_path, image_dir, sparse_dir, views, initial_poses, cams_present, camera_of, mapping, options
):
    """Rig-structured reconstruction from initial (nominal) poses: one rig (first camera = reference sensor,
    initial relative poses), one frame per group; then rounds of triangulation from the database matches and
    robust (Cauchy) bundle adjustment with shrinking reprojection thresholds."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(db_path) as db:
        for cid in cams_present:
            rec.add_camera_with_trivial_rig(db.read_camera(camera_of[cid]))
        for image in db.read_all_images():
            view = next(v for v in views if image_name(v) == image.name)
            kp = db.read_keypoints(image.image_id)[:, :2].astype(np.float64)
            im = pycolmap.Image(
                name=image.name, keypoints=kp, camera_id=image.camera_id, image_id=image.image_id
            )
            R, t = initial_poses[view]
            rec.add_image_with_trivial_frame(
                im, pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(R, float)), np.asarray(t, float))
            )
        if options.use_rig:
            ref = cams_present[0]
            ref_views = {v.group: initial_poses[v] for v in views if v.camera == ref}
            rig_config = pycolmap.RigConfig()
            rig_cams = []
            for cid in cams_present:
                rc = pycolmap.RigConfigCamera()
                rc.image_prefix = f"{cid}/"
                rc.ref_sensor = cid == ref
                if cid != ref:
                    # cam_from_ref averaged over groups is exact for a rigid nominal rig; take any group.
                    v = next(v for v in views if v.camera == cid and v.group in ref_views)
                    R, t = initial_poses[v]
                    R0, t0 = ref_views[v.group]
                    Rr = np.asarray(R) @ np.asarray(R0).T
                    rc.cam_from_rig = pycolmap.Rigid3d(
                        pycolmap.Rotation3d(Rr), np.asarray(t) - Rr @ np.asarray(t0)
                    )
                rig_cams.append(rc)
            rig_config.cameras = rig_cams
            pycolmap.apply_rig_config([rig_config], db, rec)
    rounds = max(1, options.refine_rounds)
    thresholds = np.geomspace(options.initial_max_reproj_px, options.final_max_reproj_px, rounds)
    for thr in thresholds:
        tri = mapping.triangulation
        tri.create_max_angle_error = max(2.0, float(thr))
        tri.continue_max_angle_error = max(2.0, float(thr))
        tri.merge_max_reproj_error = float(thr)
        tri.complete_max_reproj_error = float(thr)
        tri.min_angle = 1.0
        mapping.mapper.filter_max_reproj_error = float(thr)
        # COLMAP's triangulator ends with its own global refinement (default 5 x 50 non-robust BA iterations);
        # one short pass is enough to complete/merge tracks and filter, as the robust BA below follows.
        mapping.ba_global_max_refinements = options.triangulation_ba_refinements
        mapping.ba_global_max_num_iterations = options.triangulation_ba_iterations
        rec = pycolmap.triangulate_points(
            rec, db_path, image_dir, sparse_dir, clear_points=True, options=mapping
        )
        if rec.num_points3D() == 0:
            return rec
        pycolmap.bundle_adjustment(
            rec, ba_options(options, robust=True, iterations=options.round_ba_iterations)
        )
    # The last round is robust too: plain least squares let outlier tracks pull the weakly constrained rig.
    pycolmap.bundle_adjustment(rec, ba_options(options, robust=True, iterations=options.final_ba_iterations))
    return rec


def reprojection_errors(rec) -> np.ndarray:
    """Per-observation reprojection errors (pixels) of a reconstruction."""
    errs = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = image.camera
        T = image.cam_from_world()
        R, t = T.rotation.matrix(), np.asarray(T.translation)
        pts2d, pts3d = [], []
        for p in image.points2D:
            if p.has_point3D():
                pts2d.append(p.xy)
                pts3d.append(rec.points3D[p.point3D_id].xyz)
        if not pts2d:
            continue
        xc = np.asarray(pts3d) @ R.T + t
        proj = cam.img_from_cam(xc)
        errs.append(np.linalg.norm(np.asarray(proj) - np.asarray(pts2d), axis=1))
    return np.concatenate(errs) if errs else np.zeros(0)


def view_list(views: list[ViewId], limit: int = 40) -> str:
    names = [str(v) for v in views]
    return ", ".join(names[:limit]) + (f" (+{len(names) - limit} more)" if len(names) > limit else "")
