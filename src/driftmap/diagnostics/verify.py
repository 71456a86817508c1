"""Independent check of flagged double walls from the stored full-resolution frames, with Open3D.

The detector (:mod:`driftmap.diagnostics.double_wall`) works on a bounded random sample of every frame,
with its own normals, surface groups and lateral cells. :func:`verify_regions` shares none of that: per
region it reads the stored frames again (every point), places them with the revision's poses, and measures
how far layer B lies from layer A with Open3D's normal estimation, nearest-neighbour search and ICP.

Per region (see ``docs/diagnostics.md``, "Verification"):

1. **Frames**: up to ``max_frames_per_layer`` of the region's ``frames_a`` and of its ``frames_b`` -- those
   with the most stored points within ``radius_m`` of the region centre (counted on at most ~20k points of
   each frame; ties: the lower frame id). A frame listed on both layers is used on neither.
2. **Points**: every stored point of those frames within ``radius_m`` of the centre, placed with the
   revision's ``T_world_sensor``. Normals per frame, so a pose error cannot blur them (Open3D
   ``estimate_normals``, hybrid KD-tree search, on the frame's points voxel-averaged at ``normal_voxel_m`` so
   the neighbourhood does not depend on the resolution; oriented to that frame's sensor origin). Kept: normals
   within ``normal_max_angle_deg`` of the region normal (sign-free), from a sensor on the region normal's side
   of the surface (the back of a thin board is another surface).
3. **Offset** (``offset_b_minus_a_m``): for every layer-B point, the median point-to-plane distance (along
   layer A's normals, signed along the region normal) to its ``neighbours`` nearest layer-A points *across*
   the normal (Open3D ``NearestNeighborSearch`` on the points projected onto the surface plane; neighbours
   farther than ``max_lateral_m`` across or the gate along are dropped); the median over layer B. The same
   from layer A against layer B (``offset_reverse_m``) and an Open3D point-to-plane ICP of B onto A
   (``offset_icp_m``: the displacement of the region centre along the normal) are reported beside it.
4. **Confirmed** when the measured offset has the reported sign and differs from it by at most
   ``max(abs_tolerance_m, rel_tolerance * |reported|)``; a region without enough points or correspondences
   is not confirmed, and ``note`` says why.
5. **Pose or local?** (``context_offset_m``, ``pose_explained``): a pose error moves *everything* a frame sees.
   For the best-ranked frames of each layer (pairs: 1st with 1st, 2nd with 2nd, ...) the points *around* the
   region -- within ``context_radius_m`` of the centre but outside ``radius_m``, so the region itself takes no
   part -- are aligned B onto A with Open3D point-to-plane ICP, and the displacement this rigid correction
   gives the region centre along the normal (sign flipped) is the offset the surroundings explain; the median
   over the pairs is ``context_offset_m``. ``pose_explained`` is True when it agrees with the measured offset
   (same rule as 4.), False when the surroundings agree with each other (``|context_offset_m|`` within
   ``context_abs_tolerance_m``) but the region does not (a moved object, a door, a sensor artefact: the map
   *is* doubled there, but no pose correction removes it), None when undecidable (too few surrounding points
   facing the normal, ICP did not hold, or the surroundings are misaligned by another amount than the region:
   on real RGB-D data, depth distortion that changes with the viewing range moves single frames'
   surroundings too).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from driftmap.errors import ConfigError, StoreError

if TYPE_CHECKING:
    from driftmap.diagnostics.wall_results import DoubleWallRegion
    from driftmap.store.frame_store import FrameStore

logger = logging.getLogger(__name__)

_RANK_POINTS = 20_000


@dataclass(frozen=True)
class RegionCheck:
    """What the independent check measured for one region (offsets in metres, signed along its normal)."""

    region_index: int
    reported_offset_m: float
    """The detector's ``offset_b_minus_a_m``."""
    offset_b_minus_a_m: float | None
    """Median signed point-to-plane distance of layer-B points to layer A (None: unverifiable)."""
    offset_reverse_m: float | None
    """The same measured the other way round (minus the median distance of layer-A points to layer B)."""
    offset_icp_m: float | None
    """Point-to-plane ICP of B onto A: how far it moves the region centre, along the normal, sign flipped."""
    spread_m: float | None
    """1.4826 x MAD of the B-to-A distances (the layer's thickness, not the offset's uncertainty)."""
    n_points_a: int
    n_points_b: int
    n_correspondences: int
    frames_a_used: tuple[int, ...]
    frames_b_used: tuple[int, ...]
    confirmed: bool
    note: str | None = None
    context_offset_m: float | None = None
    """The offset of B from A that a rigid alignment of the two layers' surroundings explains (None: undecidable)."""
    pose_explained: bool | None = None
    """True: ``context_offset_m`` agrees with the measured offset (a pose error); False: the surroundings agree with
    each other but the region does not (local); None: undecidable or unverifiable."""

    @property
    def verifiable(self) -> bool:
        return self.offset_b_minus_a_m is not None

    def to_json(self) -> dict:
        return {
            "offset_b_minus_a_m": _num(self.offset_b_minus_a_m),
            "confirmed": bool(self.confirmed),
            "n_points_a": int(self.n_points_a),
            "n_points_b": int(self.n_points_b),
            "note": self.note,
            "offset_reverse_m": _num(self.offset_reverse_m),
            "offset_icp_m": _num(self.offset_icp_m),
            "spread_m": _num(self.spread_m),
            "n_correspondences": int(self.n_correspondences),
            "frames_a_used": [int(v) for v in self.frames_a_used],
            "frames_b_used": [int(v) for v in self.frames_b_used],
            "context_offset_m": _num(self.context_offset_m),
            "pose_explained": self.pose_explained,
        }


def _num(v: float | None) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def is_confirmed(measured_m: float | None, reported_m: float, *, abs_tolerance_m: float = 0.005,
                 rel_tolerance: float = 0.25) -> bool:
    """Same sign as ``reported_m`` and within ``max(abs_tolerance_m, rel_tolerance * |reported_m|)`` of it."""
    if measured_m is None or not math.isfinite(measured_m):
        return False
    return bool(np.sign(measured_m) == np.sign(reported_m)
                and abs(measured_m - reported_m) <= max(abs_tolerance_m, rel_tolerance * abs(reported_m)))


def verification_summary(checks: Sequence[RegionCheck], regions: Sequence[DoubleWallRegion],
                         voxels_evaluated: int) -> dict:
    """``regions_checked``, ``regions_confirmed``, ``regions_unverifiable``, ``voxels_unconfirmed`` (flagged voxels of
    the regions not confirmed) and ``fraction_unconfirmed`` (of the evaluated voxels); ``regions_local`` (confirmed,
    but the surroundings say no pose error: ``pose_explained`` False), ``voxels_local`` and ``fraction_pose``:
    the flagged voxels confirmed and not local, of the evaluated voxels -- the share a pose correction can fix."""
    if len(checks) != len(regions):
        raise ConfigError(f"verification summary: {len(checks)} checks for {len(regions)} regions")
    unconfirmed = sum(int(r.n_voxels) for c, r in zip(checks, regions) if not c.confirmed)
    local = [(c, r) for c, r in zip(checks, regions) if c.confirmed and c.pose_explained is False]
    pose = sum(int(r.n_voxels) for c, r in zip(checks, regions) if c.confirmed and c.pose_explained is not False)
    return {
        "regions_checked": len(checks),
        "regions_confirmed": sum(bool(c.confirmed) for c in checks),
        "regions_unverifiable": sum(not c.verifiable for c in checks),
        "voxels_unconfirmed": int(unconfirmed),
        "fraction_unconfirmed": unconfirmed / voxels_evaluated if voxels_evaluated else 0.0,
        "regions_local": len(local),
        "voxels_local": int(sum(int(r.n_voxels) for _, r in local)),
        "fraction_pose": pose / voxels_evaluated if voxels_evaluated else 0.0,
    }


# ---------------------------------------------------------------------------------------------- helpers


@dataclass
class _Layer:
    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    frames: tuple[int, ...]
    ranked: tuple[int, ...] = ()
    """``frames`` best first (most points near the centre)."""


def _pose_rows(store: FrameStore, frame_ids: NDArray[np.int64]) -> NDArray[np.int64]:
    all_ids = store.frame_ids
    rows = np.searchsorted(all_ids, frame_ids)
    bad = (rows >= len(all_ids)) | (all_ids[np.minimum(rows, len(all_ids) - 1)] != frame_ids)
    if bad.any():
        raise StoreError(f"{store.path}: region frame {int(frame_ids[np.argmax(bad)])} is not in the store")
    return rows


def _near_points(points_sensor: NDArray[np.float32], T: NDArray[np.float64], center_m: NDArray[np.float64],
                 radius_m: float, stride: int = 1) -> NDArray[np.float32]:
    """Every ``stride``-th stored point within ``radius_m`` of ``center_m`` (tested in the sensor frame, so only
    the kept points are ever transformed)."""
    pts = points_sensor[::stride] if stride > 1 else points_sensor
    c_s = ((center_m - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
    d = pts - c_s
    keep = np.einsum("ij,ij->i", d, d) <= np.float32(radius_m * radius_m)  # NaN rows compare False
    return pts[keep]


def _frame_normals(world: NDArray[np.float64], origin: NDArray[np.float64],
                   search: o3d.geometry.KDTreeSearchParamHybrid, voxel_m: float) -> NDArray[np.float64]:
    """Normals of one frame's points, oriented to its sensor origin. With ``voxel_m`` > 0 they are estimated on
    the points voxel-averaged at that size (the same neighbourhood at any resolution) and every point takes the
    normal of its nearest averaged point."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world))
    down = pcd.voxel_down_sample(voxel_m) if voxel_m > 0 else pcd
    down.estimate_normals(search)
    down.orient_normals_towards_camera_location(origin)
    if down is pcd:
        return np.asarray(pcd.normals)
    return _nearest_normals(world, np.asarray(down.points), np.asarray(down.normals))


def _nearest_normals(points: NDArray[np.float64], ref_points: NDArray[np.float64],
                     ref_normals: NDArray[np.float64]) -> NDArray[np.float64]:
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(ref_points))
    nns.knn_index()
    idx, _ = nns.knn_search(o3d.core.Tensor(points), 1)
    return ref_normals[idx.numpy().reshape(-1).astype(np.int64)]


def _layer(store: FrameStore, frame_ids: NDArray[np.int64], poses: NDArray[np.float64], region: DoubleWallRegion, *,
           radius_m: float, max_frames: int, cos_max: float, normal_radius_m: float, normal_max_nn: int,
           normal_voxel_m: float) -> _Layer:
    ids = np.asarray(frame_ids, dtype=np.int64)
    rows = _pose_rows(store, ids)
    center = np.asarray(region.center_m, dtype=np.float64)
    normal = np.asarray(region.normal, dtype=np.float64)
    normal = normal / max(float(np.linalg.norm(normal)), 1e-12)
    # rank the frames by their points near the centre, counted on at most ~_RANK_POINTS points per frame
    counts = np.zeros(len(ids))
    for k, (f, r) in enumerate(zip(ids, rows)):
        pts = store.frame(int(f)).points_sensor
        stride = max(1, len(pts) // _RANK_POINTS)
        counts[k] = len(_near_points(pts, poses[r], center, radius_m, stride)) * stride
    order = np.lexsort((ids, -counts))[:max_frames]  # most points near the centre; ties: lower frame id
    order = order[counts[order] > 0]
    pts_out, nrm_out, used = [], [], []
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=normal_max_nn)
    for k in order:
        T = poses[rows[k]]
        near = _near_points(store.frame(int(ids[k])).points_sensor, T, center, radius_m).astype(np.float64)
        if not len(near):
            continue
        world = near @ T[:3, :3].T + T[:3, 3]
        origin = T[:3, 3]
        n = _frame_normals(world, origin, search, normal_voxel_m)
        cos = n @ normal
        # sign-free angle test; the sensor must be on the region normal's side of the surface
        keep = (np.abs(cos) >= cos_max) & ((origin - world) @ normal > 0) & np.isfinite(n).all(axis=1)
        if keep.any():
            pts_out.append(world[keep])
            nrm_out.append(n[keep] * np.sign(cos[keep])[:, None])  # oriented along the region normal
            used.append(int(ids[k]))
    if not pts_out:
        return _Layer(np.zeros((0, 3)), np.zeros((0, 3)), ())
    return _Layer(np.concatenate(pts_out), np.concatenate(nrm_out), tuple(sorted(used)), tuple(used))


def _signed_distances(query: _Layer, reference: _Layer, normal: NDArray[np.float64], gate_m: float,
                      max_lateral_m: float, k: int) -> NDArray[np.float64]:
    """Per query point: the median point-to-plane distance (along each reference point's normal, oriented along
    the region ``normal``) to its ``k`` nearest reference points *across* the normal (Open3D nearest-neighbour
    search on the points projected onto the surface plane); neighbours more than ``max_lateral_m`` across or
    ``gate_m`` along are dropped, query points with fewer than 3 neighbours left are dropped.

    Neighbours are chosen by lateral distance only: the plain nearest 3-D neighbour prefers reference points
    whose noise put them closer to the query, which pulls every distance towards zero.
    """
    k = min(k, len(reference.points))
    proj_ref = reference.points - np.outer(reference.points @ normal, normal)
    proj_q = query.points - np.outer(query.points @ normal, normal)
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(proj_ref))
    nns.knn_index()
    idx, dist2 = nns.knn_search(o3d.core.Tensor(proj_q), k)
    j = idx.numpy().astype(np.int64).reshape(len(query.points), k)
    lateral2 = dist2.numpy().reshape(len(query.points), k)
    diff = query.points[:, None, :] - reference.points[j]
    d = np.einsum("ijk,ijk->ij", diff, reference.normals[j])
    ok = (lateral2 <= max_lateral_m * max_lateral_m) & (np.abs(d) <= gate_m)
    enough = ok.sum(axis=1) >= 3
    d = np.where(ok, d, np.nan)[enough]
    return np.nanmedian(d, axis=1) if len(d) else np.zeros(0)


def _icp_offset(a: _Layer, b: _Layer, center: NDArray[np.float64], normal: NDArray[np.float64], max_corr_m: float,
                max_iterations: int, voxel_m: float, min_fitness: float = 0.3,
                max_tilt_deg: float = 5.0) -> float | None:
    """Point-to-plane ICP of layer B onto layer A (both voxel-averaged at ``voxel_m``, normals averaged too)."""
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a.points))
    target.normals = o3d.utility.Vector3dVector(a.normals)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b.points))
    if voxel_m > 0:
        target, source = target.voxel_down_sample(voxel_m), source.voxel_down_sample(voxel_m)
        target.normalize_normals()
    reg = o3d.pipelines.registration
    result = reg.registration_icp(source, target, max_corr_m, np.eye(4), reg.TransformationEstimationPointToPlane(),
                                  reg.ICPConvergenceCriteria(max_iteration=max_iterations))
    T = np.asarray(result.transformation)
    # a turn about the normal is free on a plane and moves the centre across the normal only; a tilt of the
    # normal means ICP slid off a strip or an edge: no displacement to report
    tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, float(normal @ T[:3, :3] @ normal)))))
    if result.fitness < min_fitness or tilt_deg > max_tilt_deg:
        logger.debug("ICP rejected: fitness %.2f, tilt %.1f deg", result.fitness, tilt_deg)
        return None
    moved = T[:3, :3] @ center + T[:3, 3]
    return float(-(moved - center) @ normal)


def _context_cloud(store: FrameStore, frame_id: int, T: NDArray[np.float64], center: NDArray[np.float64], inner_m: float,
                   outer_m: float, voxel_m: float, search: o3d.geometry.KDTreeSearchParamHybrid) -> o3d.geometry.PointCloud:
    """One frame's points between ``inner_m`` and ``outer_m`` of the centre, in the world, voxel-averaged, with normals
    oriented to its sensor."""
    near = _near_points(store.frame(int(frame_id)).points_sensor, T, center, outer_m).astype(np.float64)
    world = near @ T[:3, :3].T + T[:3, 3]
    world = world[np.einsum("ij,ij->i", world - center, world - center) > inner_m * inner_m]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world)).voxel_down_sample(voxel_m)
    pcd.estimate_normals(search)
    pcd.orient_normals_towards_camera_location(T[:3, 3])
    return pcd


def _context_offset(store: FrameStore, poses: NDArray[np.float64], a: _Layer, b: _Layer, center: NDArray[np.float64],
                    normal: NDArray[np.float64], *, inner_m: float, outer_m: float, pairs: int, max_corr_m: float,
                    voxel_m: float, min_facing_points: int, cos_max: float, search: o3d.geometry.KDTreeSearchParamHybrid,
                    max_iterations: int, min_fitness: float = 0.3) -> tuple[float | None, str | None]:
    """The offset of layer B from layer A that a rigid alignment of their surroundings explains (module doc, 5.)."""
    offsets = []
    why = "no frame pair"
    reg = o3d.pipelines.registration
    for fa, fb in list(zip(a.ranked, b.ranked))[:pairs]:
        Ta, Tb = poses[_pose_rows(store, np.array([fa]))[0]], poses[_pose_rows(store, np.array([fb]))[0]]
        target = _context_cloud(store, fa, Ta, center, inner_m, outer_m, voxel_m, search)
        source = _context_cloud(store, fb, Tb, center, inner_m, outer_m, voxel_m, search)
        facing = [int(np.sum(np.abs(np.asarray(c.normals) @ normal) >= cos_max)) for c in (target, source)]
        if min(facing) < min_facing_points:
            why = f"frames {fa}/{fb}: {min(facing)} surrounding points face the normal (< {min_facing_points})"
            continue
        result = reg.registration_icp(source, target, max_corr_m, np.eye(4), reg.TransformationEstimationPointToPlane(),
                                      reg.ICPConvergenceCriteria(max_iteration=max_iterations))
        if result.fitness < min_fitness:
            why = f"frames {fa}/{fb}: surroundings overlap {result.fitness:.2f} after ICP (< {min_fitness})"
            continue
        T = np.asarray(result.transformation)
        offsets.append(float(-((T[:3, :3] @ center + T[:3, 3]) - center) @ normal))
    if not offsets:
        return None, why
    return float(np.median(offsets)), None


def _context_verdict(ctx: float | None, why: str | None, measured: float, abs_tolerance_m: float,
                     rel_tolerance: float) -> tuple[bool | None, str | None]:
    """``(pose_explained, note)`` from the surroundings' offset ``ctx`` against the region's ``measured`` one: the
    same offset (a pose error of these frames), surroundings that agree (a local change or artefact), or neither."""
    if ctx is None:
        return None, f"pose or local: undecidable ({why})"
    if is_confirmed(ctx, measured, abs_tolerance_m=abs_tolerance_m, rel_tolerance=rel_tolerance):
        return True, None
    if abs(ctx) <= abs_tolerance_m:
        return False, (f"the surroundings agree ({100 * ctx:+.1f} cm) but the region is {100 * measured:+.1f} cm off: "
                       f"not a pose error of these frames (a local change or artefact)")
    # the surroundings are misaligned too, by another amount: neither call is supported
    return None, (f"pose or local: undecidable (the surroundings are {100 * ctx:+.1f} cm off, the region "
                  f"{100 * measured:+.1f} cm)")


# ---------------------------------------------------------------------------------------------- verify


# 81 lines, 8 of them its keyword settings: the five steps of the module doc per region read best in one loop
def verify_regions(store: FrameStore, revision: int, regions: Sequence[DoubleWallRegion], *, radius_m: float = 0.3,
                   max_frames_per_layer: int = 6, normal_max_angle_deg: float = 25.0, normal_radius_m: float = 0.05,
                   normal_max_nn: int = 30, normal_voxel_m: float = 0.02, min_points_per_layer: int = 100,
                   min_correspondences: int = 50, gate_m: float | None = None, max_lateral_m: float = 0.03,
                   neighbours: int = 8, icp: bool = True, icp_max_iterations: int = 30, abs_tolerance_m: float = 0.005,
                   rel_tolerance: float = 0.25, context: bool = True, context_radius_m: float = 3.0,
                   context_pairs: int = 3, context_voxel_m: float = 0.03, context_min_facing_points: int = 100,
                   context_abs_tolerance_m: float = 0.01, context_rel_tolerance: float = 0.35) -> list[RegionCheck]:
    """Check every region against the stored frames placed with ``revision``'s poses (see the module doc).

    ``gate_m`` (default ``2 |reported offset| + 2 cm``, symmetric about zero, so it does not favour the
    reported value) bounds the point-to-plane distances used and is ICP's maximum correspondence distance.
    ``context`` adds step 5 (the surroundings within ``context_radius_m``, ``context_pairs`` frame pairs);
    ``pose_explained`` uses ``max(context_abs_tolerance_m, context_rel_tolerance * |measured|)``.
    """
    if radius_m <= 0 or normal_radius_m <= 0 or max_lateral_m <= 0:
        raise ConfigError(f"verify_regions: radius_m, normal_radius_m and max_lateral_m must be positive "
                          f"(got {radius_m}, {normal_radius_m}, {max_lateral_m})")
    if max_frames_per_layer < 1 or not 0 < normal_max_angle_deg < 90:
        raise ConfigError(f"verify_regions: max_frames_per_layer >= 1 and 0 < normal_max_angle_deg < 90 "
                          f"(got {max_frames_per_layer}, {normal_max_angle_deg})")
    poses = store.poses(int(revision))
    cos_max = math.cos(math.radians(normal_max_angle_deg))
    checks = []
    for k, region in enumerate(regions):
        reported = float(region.offset_b_minus_a_m)
        normal = np.asarray(region.normal, dtype=np.float64)
        normal = normal / max(float(np.linalg.norm(normal)), 1e-12)
        center = np.asarray(region.center_m, dtype=np.float64)
        gate = float(gate_m) if gate_m is not None else 2.0 * abs(reported) + 0.02
        kw = dict(radius_m=radius_m, max_frames=max_frames_per_layer, cos_max=cos_max, normal_radius_m=normal_radius_m,
                  normal_max_nn=normal_max_nn, normal_voxel_m=normal_voxel_m)
        fa, fb = np.asarray(region.frames_a, dtype=np.int64), np.asarray(region.frames_b, dtype=np.int64)
        both = np.intersect1d(fa, fb)  # a frame on both layers (in different voxels) says nothing about either
        a = _layer(store, np.setdiff1d(fa, both), poses, region, **kw)
        b = _layer(store, np.setdiff1d(fb, both), poses, region, **kw)
        base = dict(region_index=k, reported_offset_m=reported, n_points_a=len(a.points), n_points_b=len(b.points),
                    frames_a_used=a.frames, frames_b_used=b.frames)
        few = [f"layer {name}: {len(layer.points)} points" for name, layer in (("A", a), ("B", b))
               if len(layer.points) < min_points_per_layer]
        if few:
            note = (f"{'; '.join(few)} within {radius_m:g} m with a normal within {normal_max_angle_deg:g} deg "
                    f"(< {min_points_per_layer})")
            checks.append(RegionCheck(offset_b_minus_a_m=None, offset_reverse_m=None, offset_icp_m=None, spread_m=None,
                                      n_correspondences=0, confirmed=False, note=note, **base))
            logger.info("region %d: unverifiable (%s)", k, note)
            continue
        d_ba = _signed_distances(b, a, normal, gate, max_lateral_m, neighbours)
        if len(d_ba) < min_correspondences:
            note = (f"{len(d_ba)} layer-B points have a layer-A point within {max_lateral_m:g} m across and "
                    f"{gate:g} m along the normal (< {min_correspondences})")
            checks.append(RegionCheck(offset_b_minus_a_m=None, offset_reverse_m=None, offset_icp_m=None, spread_m=None,
                                      n_correspondences=len(d_ba), confirmed=False, note=note, **base))
            logger.info("region %d: unverifiable (%s)", k, note)
            continue
        measured = float(np.median(d_ba))
        spread = float(1.4826 * np.median(np.abs(d_ba - measured)))
        d_ab = _signed_distances(a, b, normal, gate, max_lateral_m, neighbours)
        reverse = float(-np.median(d_ab)) if len(d_ab) >= min_correspondences else None
        icp_off = _icp_offset(a, b, center, normal, gate, icp_max_iterations, normal_voxel_m) if icp else None
        ok = is_confirmed(measured, reported, abs_tolerance_m=abs_tolerance_m, rel_tolerance=rel_tolerance)
        notes = []
        if not ok:
            notes.append(f"measured {100 * measured:+.1f} cm, reported {100 * reported:+.1f} cm "
                         f"(tolerance {100 * max(abs_tolerance_m, rel_tolerance * abs(reported)):.1f} cm)")
        ctx = explained = None
        if context:
            ctx, why = _context_offset(
                store, poses, a, b, center, normal, inner_m=radius_m, outer_m=context_radius_m, pairs=context_pairs,
                max_corr_m=gate, voxel_m=context_voxel_m, min_facing_points=context_min_facing_points, cos_max=cos_max,
                search=o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * context_voxel_m, max_nn=normal_max_nn),
                max_iterations=icp_max_iterations)
            explained, note = _context_verdict(ctx, why, measured, context_abs_tolerance_m, context_rel_tolerance)
            if note is not None:
                notes.append(note)
        checks.append(RegionCheck(offset_b_minus_a_m=measured, offset_reverse_m=reverse, offset_icp_m=icp_off,
                                  spread_m=spread, n_correspondences=len(d_ba), confirmed=ok,
                                  note="; ".join(notes) or None, context_offset_m=ctx, pose_explained=explained, **base))
        logger.info("region %d: reported %+.4f m, measured %+.4f m (reverse %s, ICP %s, surroundings %s), %s", k, reported,
                    measured, reverse, icp_off, ctx, "confirmed" if ok else "NOT confirmed")
    return checks
