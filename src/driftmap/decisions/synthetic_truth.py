"""The true answer to an action query in the synthetic room (``driftmap synth``'s scene, the embedded
``datasets/synthetic-loop``): what a noise-free, drift-free map made from the same views would decide.

The truth has two parts, neither taken from a driftmap map:

- **geometry**: the room's boxes (:func:`driftmap.sources.synthetic.scene_boxes`; the glass pane is a solid too):
  exact distances from points and footprints to them, their faces for surfaces;
- **what the camera could see**: the true depth image of every frame, rendered from its ground-truth pose with
  every pixel (the glass gives no reading, as in the log), and the layers' max range. A point of space is *seen*
  when some frame's pixel it projects to measures a depth beyond it within the max range (a z-buffer test on the
  voxel lattice's centres: :attr:`SceneTruth.seen`); a point of a surface when the pixel measures it (within 1 cm).

Unknown space in the truth is what no frame saw. The truth functions take a tolerance ``delta_m`` and return None
when the answer changes within it (a sphere or footprint grown or shrunk by it, a ROI or patch grown or shrunk by
it, a fraction within ``delta_fraction`` of the threshold): such a query has no unambiguous answer at the map's
resolution, and the query generator leaves it out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from driftmap.decisions.query_file import ClearanceQuery, CollisionQuery, ExploreQuery, FootholdQuery, GraspQuery
from driftmap.decisions.space import footprint_signed_distance, path_samples
from driftmap.decisions.surface import dominant_normal

SURFACE_STEP_M = 0.005
"""Faces are sampled on this grid (m) for the surface truths."""
SURFACE_TOLERANCE_M = 0.01
"""A face sample is measured by a pixel whose true depth lies within this of it."""


@numba.njit(parallel=True, cache=True)
def _seen_kernel(points, R_cw, t_cw, origins, depth, fx, fy, cx, cy, max_range, tol, surface, out):
    """out[i] = some frame's pixel sees points[i]: in front of its measured depth (``surface`` False) or on it
    within ``tol`` (True), within ``max_range`` of the camera."""
    n_frames, h, w = depth.shape
    for i in numba.prange(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for f in range(n_frames):
            dx, dy, dz = px - origins[f, 0], py - origins[f, 1], pz - origins[f, 2]
            if dx * dx + dy * dy + dz * dz > max_range * max_range:
                continue
            z = R_cw[f, 2, 0] * px + R_cw[f, 2, 1] * py + R_cw[f, 2, 2] * pz + t_cw[f, 2]
            if z <= 1e-6:
                continue
            x = R_cw[f, 0, 0] * px + R_cw[f, 0, 1] * py + R_cw[f, 0, 2] * pz + t_cw[f, 0]
            y = R_cw[f, 1, 0] * px + R_cw[f, 1, 1] * py + R_cw[f, 1, 2] * pz + t_cw[f, 1]
            u = int(np.floor(fx * x / z + cx + 0.5))
            v = int(np.floor(fy * y / z + cy + 0.5))
            if u < 0 or u >= w or v < 0 or v >= h:
                continue
            d = depth[f, v, u]
            if not np.isfinite(d):
                continue
            if (abs(d - z) <= tol) if surface else (z < d):
                out[i] = True
                break


@dataclass
class SceneTruth:
    """The room's solids, the frames' true depth images and the lattice of seen voxel centres."""

    box_min: NDArray[np.float64]
    box_max: NDArray[np.float64]
    names: list[str]
    poses: NDArray[np.float64]
    depth: NDArray[np.float32]
    intrinsics: tuple[float, float, float, float]
    max_range_m: float
    voxel_m: float
    origin_index: NDArray[np.int64]
    seen: NDArray[np.bool_]
    """per lattice voxel of the truth grid (``origin_index`` + shape), whether its centre was seen"""

    @classmethod
    def from_log(cls, log_dir: str | Path, max_range_m: float, voxel_m: float = 0.02) -> SceneTruth:
        from driftmap.sources.synthetic import ROOM_MAX_M, ROOM_MIN_M, SyntheticLog, scene_boxes
        from driftmap.sources.synthetic_scene import build_scene

        log = SyntheticLog(Path(log_dir))
        cfg = log.config
        boxes = scene_boxes()
        scene, glass_ids = build_scene(cfg)
        poses = np.asarray(log.ground_truth().poses, dtype=np.float64)
        depth = np.stack([_true_depth(scene, glass_ids, T, cfg) for T in poses])
        lo = np.floor((np.asarray(ROOM_MIN_M) - 0.2) / voxel_m).astype(np.int64)
        hi = np.floor((np.asarray(ROOM_MAX_M) + 0.2) / voxel_m).astype(np.int64)
        truth = cls(np.array([b.min_m for b in boxes]), np.array([b.max_m for b in boxes]), [b.name for b in boxes],
                    poses, depth, (cfg.fx, cfg.fy, cfg.cx, cfg.cy), float(max_range_m), float(voxel_m), lo,
                    np.zeros(0, bool))
        shape = hi - lo + 1
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
        truth.seen = truth.sees((idx + lo + 0.5) * voxel_m).reshape(tuple(shape))
        return truth

    # ---------------------------------------------------------------------------------------- seeing
    def sees(self, points: NDArray[np.float64], *, surface: bool = False) -> NDArray[np.bool_]:
        """Which points some frame saw (free space in front of a measured depth, or ``surface`` points measured)."""
        pts = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float64)
        R_cw = np.ascontiguousarray(np.transpose(self.poses[:, :3, :3], (0, 2, 1)))
        t_cw = -np.einsum("fij,fj->fi", R_cw, self.poses[:, :3, 3])
        out = np.zeros(len(pts), dtype=np.bool_)
        fx, fy, cx, cy = self.intrinsics
        _seen_kernel(pts, R_cw, np.ascontiguousarray(t_cw), np.ascontiguousarray(self.poses[:, :3, 3]), self.depth,
                     fx, fy, cx, cy, self.max_range_m, SURFACE_TOLERANCE_M, surface, out)
        return out

    def seen_at(self, lattice: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Whether lattice voxels' centres were seen (outside the truth grid: not)."""
        idx = np.atleast_2d(lattice) - self.origin_index
        inside = np.all((idx >= 0) & (idx < np.asarray(self.seen.shape)), axis=1)
        out = np.zeros(len(idx), bool)
        out[inside] = self.seen[tuple(idx[inside].T)]
        return out

    # ---------------------------------------------------------------------------------------- geometry
    def distance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Signed distance from each point to the nearest solid (negative inside one)."""
        p = np.atleast_2d(points)[:, None, :]
        d = np.maximum(self.box_min[None] - p, p - self.box_max[None])  # (N, B, 3)
        outside = np.linalg.norm(np.maximum(d, 0.0), axis=2)
        signed = np.where(np.all(d <= 0, axis=2), d.max(axis=2), outside)
        return signed.min(axis=1)

    def nearest_solid(self, point: NDArray[np.float64]) -> str:
        p = np.asarray(point)[None]
        d = np.linalg.norm(np.maximum(np.maximum(self.box_min - p, p - self.box_max), 0.0), axis=1)
        return self.names[int(np.argmin(d))]

    def face_samples(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Points on the solids' faces inside the box ``lo .. hi`` (every :data:`SURFACE_STEP_M`), with the faces'
        outward normals; faces inside another solid are left out."""
        pts, normals = [], []
        s = SURFACE_STEP_M
        for bmin, bmax in zip(self.box_min, self.box_max):
            a, b = np.maximum(bmin, lo), np.minimum(bmax, hi)
            if np.any(a > b):
                continue
            for axis in range(3):
                for side, value in ((-1.0, bmin[axis]), (1.0, bmax[axis])):
                    if not a[axis] <= value <= b[axis]:
                        continue
                    others = [k for k in range(3) if k != axis]
                    grids = [np.arange(a[k] + s / 2, b[k], s) for k in others]
                    if any(len(g) == 0 for g in grids):
                        continue
                    g0, g1 = np.meshgrid(*grids, indexing="ij")
                    p = np.empty((g0.size, 3))
                    p[:, axis], p[:, others[0]], p[:, others[1]] = value, g0.ravel(), g1.ravel()
                    nrm = np.zeros(3)
                    nrm[axis] = side
                    pts.append(p)
                    normals.append(np.broadcast_to(nrm, p.shape))
        if not pts:
            return np.zeros((0, 3)), np.zeros((0, 3))
        p, n = np.concatenate(pts), np.concatenate(normals)
        exposed = self.distance(p + 0.5 * s * n) > 0  # a face inside (or against) another solid is no surface
        return p[exposed], n[exposed]

    def visible_faces(self, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p, n = self.face_samples(lo, hi)
        if len(p) == 0:
            return p, n
        seen = self.sees(p, surface=True)
        return p[seen], n[seen]


def _true_depth(scene: o3d.t.geometry.RaycastingScene, glass_ids: set[int], T: NDArray[np.float64], cfg) -> NDArray[np.float32]:
    """The noise-free z-depth image from pose ``T`` (NaN: no reading -- glass, nothing hit, beyond the sensor)."""
    u, v = np.meshgrid(np.arange(cfg.width, dtype=np.float64), np.arange(cfg.height, dtype=np.float64))
    rays = np.stack([(u - cfg.cx) / cfg.fx, (v - cfg.cy) / cfg.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    dirs = rays @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], dirs.shape)
    ans = scene.cast_rays(o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32)))
    z = ans["t_hit"].numpy().astype(np.float64)
    gid = ans["geometry_ids"].numpy()
    bad = ~np.isfinite(z) | (z > cfg.max_range_m)
    for g in glass_ids:
        bad |= gid == g
    return np.where(bad, np.nan, z).astype(np.float32).reshape(cfg.height, cfg.width)


# ---------------------------------------------------------------------------------------------------- truths
def _ball_unseen(truth: SceneTruth, points: NDArray[np.float64], radius_m: float) -> bool:
    """Whether an unseen lattice voxel's cube lies within ``radius_m`` of any point (as the map's clearance counts
    unknown space; the voxel holding a point always)."""
    vs = truth.voxel_m
    for p in points:
        lo = np.floor((p - radius_m) / vs).astype(np.int64)
        hi = np.floor((p + radius_m) / vs).astype(np.int64)
        idx = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
        gap = np.maximum(np.maximum(idx * vs - p, p - (idx + 1) * vs), 0.0)
        near = np.linalg.norm(gap, axis=1) <= radius_m
        if not np.all(truth.seen_at(idx[near])):
            return True
    return False


def _seen_surface(truth: SceneTruth, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> cKDTree | None:
    """A KD-tree of the seen face samples in a box (None when there are none)."""
    p, _ = truth.visible_faces(lo, hi)
    return cKDTree(p) if len(p) else None


def clearance_truth(truth: SceneTruth, q: ClearanceQuery, delta_m: float) -> dict | None:
    """``blocked`` when a seen surface is within the radius of a point, else ``unknown`` when unseen space is
    within it, else ``free``; None when that changes with the radius grown or shrunk by ``delta_m``. A solid within
    the radius whose near side nobody saw is unseen space (the map cannot know it): ``physically_blocked`` records
    the geometry alone."""
    lo, hi = q.extent_m()
    tree = _seen_surface(truth, lo - delta_m, hi + delta_m)
    d_seen = float(tree.query(q.points_m)[0].min()) if tree is not None else np.inf
    d = float(truth.distance(q.points_m).min())

    def label(r: float) -> str:
        if d_seen <= r:
            return "blocked"
        return "unknown" if _ball_unseen(truth, q.points_m, r) else "free"

    labels = {label(q.radius_m + s) for s in (-delta_m, 0.0, delta_m)}
    if len(labels) != 1:
        return None
    return {"decision": labels.pop(), "clearance_m": d, "seen_clearance_m": d_seen,
            "physically_blocked": bool(d < q.radius_m)}


def _grown(q: CollisionQuery, grow: float) -> CollisionQuery:
    size = tuple(v + 2 * grow for v in q.size_m) if q.footprint == "box" else (q.size_m[0] + grow, q.size_m[1] + 2 * grow)
    return CollisionQuery(q.id, q.kind, q.path_m, q.footprint, size)


def _sweep_truth(truth: SceneTruth, q: CollisionQuery, samples: NDArray[np.float64], surface: NDArray[np.float64],
                 tree: cKDTree | None) -> tuple[int | None, int | None, int | None]:
    """First sample index where the footprint holds a seen surface sample, an unseen voxel centre, and where it
    overlaps a solid at all."""
    first_c = first_u = first_p = None
    bound = float(np.linalg.norm(q.half_extent_m))
    for i, s in enumerate(samples):
        if first_c is None and tree is not None:
            near = tree.query_ball_point(s, bound)
            if near and np.any(footprint_signed_distance(q, surface[near] - s) < 0):
                first_c = i
        if first_u is None and _footprint_unseen(truth, q, s):
            first_u = i
        if first_p is None and _footprint_hits_solid(truth, q, s):
            first_p = i
        if first_c is not None and first_u is not None and first_p is not None:
            break
    return first_c, first_u, first_p


def _footprint_hits_solid(truth: SceneTruth, q: CollisionQuery, s: NDArray[np.float64]) -> bool:
    """Whether the footprint centred at ``s`` overlaps a solid (box against box; cylinder against box)."""
    if q.footprint == "box":
        h = 0.5 * np.asarray(q.size_m)
        return bool(np.any(np.all((s - h < truth.box_max) & (s + h > truth.box_min), axis=1)))
    r, height = q.size_m
    z_overlap = (s[2] - 0.5 * height < truth.box_max[:, 2]) & (s[2] + 0.5 * height > truth.box_min[:, 2])
    closest = np.clip(s[:2], truth.box_min[:, :2], truth.box_max[:, :2])
    return bool(np.any(z_overlap & (np.linalg.norm(closest - s[:2], axis=1) < r)))


def _footprint_unseen(truth: SceneTruth, q: CollisionQuery, s: NDArray[np.float64]) -> bool:
    vs = truth.voxel_m
    half = q.half_extent_m
    lo = np.floor((s - half) / vs).astype(np.int64)  # the voxels whose cubes the footprint overlaps, as the map's sweep
    hi = np.floor((s + half) / vs).astype(np.int64)
    idx = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
    if q.footprint == "cylinder":
        gap = np.maximum(np.maximum(idx[:, :2] * vs - s[:2], s[:2] - (idx[:, :2] + 1) * vs), 0.0)
        idx = idx[np.linalg.norm(gap, axis=1) <= q.size_m[0]]
    return not bool(np.all(truth.seen_at(idx)))


def collision_truth(truth: SceneTruth, q: CollisionQuery, delta_m: float, step_m: float) -> dict | None:
    """The first place along the path where the footprint holds a seen surface (``blocked``) or unseen space
    (``unknown``), whichever comes first (a contact wins a tie), as the map's sweep; None when the decision changes
    with the footprint grown or shrunk by ``delta_m``. ``physical_contact_m``: where the footprint first overlaps a
    solid at all (seen or not)."""
    samples, along = path_samples(q.path_m, step_m)
    lo, hi = q.extent_m()
    surface, _ = truth.visible_faces(lo - delta_m, hi + delta_m)
    tree = cKDTree(surface) if len(surface) else None
    results = []
    for grow in (-delta_m, 0.0, delta_m):
        c, u, p = _sweep_truth(truth, _grown(q, grow), samples, surface, tree)
        if c is not None and (u is None or c <= u):
            results.append(("blocked", c, p))
        elif u is not None:
            results.append(("unknown", u, p))
        else:
            results.append(("free", None, p))
    if len({r[0] for r in results}) != 1:
        return None
    decision, at, phys = results[1]
    return {"decision": decision, "contact_distance_m": None if at is None else float(along[at]),
            "physical_contact_m": None if phys is None else float(along[phys])}


def _surface_stats(normals: NDArray[np.float64], points: NDArray[np.float64]) -> tuple[float, float, float]:
    """Fraction of samples off the dominant normal, slope of the dominant normal (deg), RMS offset from the plane."""
    e, angles = dominant_normal(normals)
    if e[2] < 0:
        e_up = -e
    else:
        e_up = e
    along = points @ e
    flat = float(np.sqrt(np.mean((along - np.median(along)) ** 2)))
    slope = float(np.degrees(np.arccos(np.clip(abs(e_up[2]), 0.0, 1.0))))
    return float(np.mean(angles > 10.0)), slope, flat


MIN_SURFACE_M2 = 0.0015
"""A region whose seen surface is below this area (15 cm^2) is ``too_few_points`` in the truth; above it
(at least :data:`ENOUGH_SURFACE_M2`) it has a surface to decide on."""
ENOUGH_SURFACE_M2 = 0.003


def _faces_in(truth: SceneTruth, lo: NDArray[np.float64], hi: NDArray[np.float64],
              keep=None) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """The seen face samples inside a box (and ``keep(points)``), their normals and their area (m^2)."""
    p, n = truth.visible_faces(lo, hi)
    if keep is not None and len(p):
        mask = keep(p)
        p, n = p[mask], n[mask]
    return p, n, len(p) * SURFACE_STEP_M**2


def grasp_truth(truth: SceneTruth, q: GraspQuery, delta_m: float) -> dict | None:
    """``too_few_points`` when the ROI grown by ``delta_m`` holds (nearly) no seen surface; else, with at least
    :data:`ENOUGH_SURFACE_M2` of it in the ROI, ``graspable`` when under 3 % of the seen surface in the grown ROI
    faces another way than the dominant face (the map's normals borrow from that far), ``unstable_normal`` when at
    least 25 % does in the ROI and 20 % in the grown one; None otherwise."""
    _, _, area_grown = _faces_in(truth, q.roi_min_m - delta_m, q.roi_max_m + delta_m)
    if area_grown < MIN_SURFACE_M2:
        return {"decision": "too_few_points", "surface_m2": area_grown}
    p, n, area = _faces_in(truth, q.roi_min_m, q.roi_max_m)
    if area < ENOUGH_SURFACE_M2:
        return None
    off, _, _ = _surface_stats(n, p)
    pg, ng, _ = _faces_in(truth, q.roi_min_m - delta_m, q.roi_max_m + delta_m)
    off_grown, _, _ = _surface_stats(ng, pg)
    normal = dominant_normal(n)[0].tolist()
    if off_grown <= 0.03:
        return {"decision": "graspable", "normal": normal, "surface_m2": area}
    if off >= 0.25 and off_grown >= 0.2:
        return {"decision": "unstable_normal", "off_dominant_fraction": off, "surface_m2": area}
    return None


def foothold_truth(truth: SceneTruth, q: FootholdQuery, delta_m: float, max_flatness_m: float) -> dict | None:
    """The patch's seen surface (the map's cylinder: radius r, height 2 r): ``too_few_points`` when the patch grown
    by ``delta_m`` holds (nearly) none; else judged on the patch and the grown patch (and the shrunk one when it
    keeps 4 cm): ``uneven`` when the RMS offset from the dominant plane exceeds twice ``max_flatness_m`` in each,
    ``too_steep`` / ``stable`` when each is flat within half ``max_flatness_m`` and the slope lies 10 deg or more from
    the limit; None otherwise."""
    def patch(r: float) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        keep = lambda p: (np.linalg.norm(p[:, :2] - q.center_m[:2], axis=1) <= r) & (np.abs(p[:, 2] - q.center_m[2]) <= r)
        return _faces_in(truth, q.center_m - r, q.center_m + r, keep)

    if patch(q.radius_m + delta_m)[2] < MIN_SURFACE_M2:
        return {"decision": "too_few_points"}
    labels = set()
    radii = [q.radius_m, q.radius_m + delta_m] + ([q.radius_m - delta_m] if q.radius_m - delta_m >= 0.04 else [])
    for r in radii:
        p, n, area = patch(r)
        if area < ENOUGH_SURFACE_M2:
            return None
        _, slope, flat = _surface_stats(n, p)
        if flat > 2 * max_flatness_m:
            labels.add("uneven")
        elif flat > 0.5 * max_flatness_m or abs(slope - q.max_slope_deg) < 10.0:
            return None
        else:
            labels.add("too_steep" if slope > q.max_slope_deg else "stable")
    if len(labels) != 1:
        return None
    return {"decision": labels.pop()}


def explore_truth(truth: SceneTruth, q: ExploreQuery, delta_fraction: float) -> dict | None:
    """The fraction of the region's lattice voxel centres nobody saw (the map's voxels), ``go_look`` above the
    threshold; None within ``delta_fraction`` of it."""
    vs = truth.voxel_m
    lo = np.ceil(q.min_m / vs - 0.5).astype(np.int64)
    hi = np.floor(q.max_m / vs - 0.5).astype(np.int64)
    if np.any(hi < lo):
        return None
    idx = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
    fraction = float(1.0 - truth.seen_at(idx).mean())
    if abs(fraction - q.max_unknown_fraction) < delta_fraction:
        return None
    return {"decision": "go_look" if fraction > q.max_unknown_fraction else "known", "unknown_fraction": fraction}
