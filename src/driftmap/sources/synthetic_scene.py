"""The synthetic log's world: the furnished room and the city block as axis-aligned boxes, and the ray-casting scene
built from them (:mod:`driftmap.sources.synthetic`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from driftmap.errors import SourceError
from driftmap.sources.synthetic_config import SyntheticLogConfig
from driftmap.sources.synthetic_motion import STREET_HALF_SIZE_M


@dataclass(frozen=True)
class SceneBox:
    name: str
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    glass: bool = False


ROOM_MIN_M = (-3.0, -2.5, 0.0)
ROOM_MAX_M = (3.0, 2.5, 2.6)
WALL_THICKNESS_M = 0.1
DOOR_RECESS_M = 0.05
BOARD_THICKNESS_M = 0.02
CHAIR_MOVE_M = (-2.775, 2.225)
"""``chair_moved``: the chair's shift in x, y (from its place near the -y wall, centre (1.025, -1.775), to the free
floor before the -x wall, centre (-1.75, 0.45))."""
CORRIDOR_DEPTH_M = 1.5
"""``door_open``: the corridor behind the +x wall's door is this deep (its back wall ends the rays through the door)."""


def scene_boxes(*, door_open: bool = False, chair_moved: bool = False) -> list[SceneBox]:
    """The room as axis-aligned boxes (world frame, z up, floor at z = 0).

    ``door_open``: the +x wall's door panel is left out and a corridor stands behind the opening (floor, ceiling, side
    walls and a back wall :data:`CORRIDOR_DEPTH_M` away), so rays through the door see free space where the closed
    panel stands. ``chair_moved``: the chair stands elsewhere (:data:`CHAIR_MOVE_M`). Two sessions of one room whose
    world changed between them (issue 26: change vs misalignment); the defaults are the room as it always was."""
    (x0, y0, z0), (x1, y1, z1) = ROOM_MIN_M, ROOM_MAX_M
    w = WALL_THICKNESS_M
    door_y, door_h = (-0.45, 0.45), 2.0
    boxes = [
        SceneBox("floor", (x0 - w, y0 - w, z0 - w), (x1 + w, y1 + w, z0)),
        SceneBox("ceiling", (x0 - w, y0 - w, z1), (x1 + w, y1 + w, z1 + w)),
        SceneBox("wall_-x", (x0 - w, y0 - w, z0), (x0, y1 + w, z1)),
        SceneBox("wall_-y", (x0 - w, y0 - w, z0), (x1 + w, y0, z1)),
        SceneBox("wall_+y", (x0 - w, y1, z0), (x1 + w, y1 + w, z1)),
        # +x wall with a door opening; the door panel sits DOOR_RECESS_M behind the wall face
        SceneBox("wall_+x_left", (x1, y0 - w, z0), (x1 + w, door_y[0], z1)),
        SceneBox("wall_+x_right", (x1, door_y[1], z0), (x1 + w, y1 + w, z1)),
        SceneBox("wall_+x_top", (x1, door_y[0], door_h), (x1 + w, door_y[1], z1)),
        SceneBox("door_panel", (x1 + DOOR_RECESS_M, door_y[0], z0), (x1 + DOOR_RECESS_M + 0.04, door_y[1], door_h)),
        # a glass pane just in front of the -x wall: the depth camera gets no reading there
        SceneBox("glass", (x0, -1.0, 0.8), (x0 + 0.01, 0.0, 1.8), glass=True),
        # table near the +y wall
        SceneBox("table_top", (-0.6, 1.4, 0.72), (0.6, 2.2, 0.76)),
        *[
            SceneBox(f"table_leg_{i}", (lx, ly, 0.0), (lx + 0.05, ly + 0.05, 0.72))
            for i, (lx, ly) in enumerate([(-0.6, 1.4), (0.55, 1.4), (-0.6, 2.15), (0.55, 2.15)])
        ],
        # chair near the -y wall: thin legs (2.4 cm) and a seat
        SceneBox("chair_seat", (0.8, -2.0, 0.45), (1.25, -1.55, 0.48)),
        *[
            SceneBox(f"chair_leg_{i}", (lx, ly, 0.0), (lx + 0.024, ly + 0.024, 0.45))
            for i, (lx, ly) in enumerate([(0.8, -2.0), (1.226, -2.0), (0.8, -1.574), (1.226, -1.574)])
        ],
        # a 2 cm board standing half a metre in front of the -y wall
        SceneBox("thin_board", (-1.8, -2.0 - BOARD_THICKNESS_M, 0.0), (-0.8, -2.0, 1.2)),
        # furniture along the walls: every view sees structure in all directions, so registration is
        # well-posed (a bare wall plus floor leaves the slide along the wall unobservable)
        SceneBox("shelf_-x", (x0, 1.0, 0.0), (x0 + 0.4, 2.0, 1.8)),
        SceneBox("crate_-x", (x0, -2.3, 0.0), (x0 + 0.3, -1.6, 0.9)),
        SceneBox("cabinet_+x", (x1 - 0.45, 1.2, 0.0), (x1, 2.2, 0.9)),
        SceneBox("locker_+x", (x1 - 0.4, -2.4, 0.0), (x1, -1.6, 2.0)),
        SceneBox("wall_shelf_-y", (1.8, y0, 1.2), (2.6, y0 + 0.3, 1.6)),
        SceneBox("pillar_-y", (-2.2, y0, 0.0), (-1.95, y0 + 0.25, z1)),
        SceneBox("sideboard_+y", (1.0, y1 - 0.4, 0.0), (2.2, y1, 0.85)),
        SceneBox("pillar_+y", (x0 + 0.05, y1 - 0.3, 0.0), (x0 + 0.3, y1, z1)),
        SceneBox("lamp", (-0.3, -0.3, z1 - 0.3), (0.3, 0.3, z1)),
    ]
    if chair_moved:
        dx, dy = CHAIR_MOVE_M
        boxes = [SceneBox(b.name, (b.min_m[0] + dx, b.min_m[1] + dy, b.min_m[2]),
                          (b.max_m[0] + dx, b.max_m[1] + dy, b.max_m[2]))
                 if b.name.startswith("chair_") else b for b in boxes]
    if door_open:
        xb, yc = x1 + w, 1.0  # the corridor: beyond the wall, 2 m wide (the door is 0.9 m)
        boxes = [b for b in boxes if b.name != "door_panel"] + [
            SceneBox("corridor_floor", (xb, -yc - w, z0 - w), (xb + CORRIDOR_DEPTH_M + w, yc + w, z0)),
            SceneBox("corridor_ceiling", (xb, -yc - w, z1), (xb + CORRIDOR_DEPTH_M + w, yc + w, z1 + w)),
            SceneBox("corridor_-y", (xb, -yc - w, z0), (xb + CORRIDOR_DEPTH_M + w, -yc, z1)),
            SceneBox("corridor_+y", (xb, yc, z0), (xb + CORRIDOR_DEPTH_M + w, yc + w, z1)),
            SceneBox("corridor_back", (xb + CORRIDOR_DEPTH_M, -yc, z0), (xb + CORRIDOR_DEPTH_M + w, yc, z1)),
        ]
    return boxes


STREET_FACADE_OFFSET_M = 7.0
"""Building facades stand this far from the road's centreline (+- 1 m per building)."""


def street_boxes(seed: int) -> list[SceneBox]:
    """The city block of ``scene="street"`` (world frame, z up, ground at z = 0): buildings of random width, depth
    and height inside and outside the road loop, with gaps between them, poles on both sides and parked cars,
    all drawn from ``seed`` (so the same seed gives the same town)."""
    rng = np.random.default_rng([seed, 20261123])
    a, b = STREET_HALF_SIZE_M
    d = STREET_FACADE_OFFSET_M
    boxes = [SceneBox("ground", (-a - 60, -b - 60, -0.2), (a + 60, b + 60, 0.0))]

    def along(side: str, t0: float, t1: float, off0: float, off1: float, z1: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """A box spanning ``t0..t1`` along a side of the loop and ``off0..off1`` outwards from its centreline."""
        lo, hi = min(off0, off1), max(off0, off1)
        if side == "-y":
            return (t0, -b - hi, 0.0), (t1, -b - lo, z1)
        if side == "+y":
            return (t0, b + lo, 0.0), (t1, b + hi, z1)
        if side == "-x":
            return (-a - hi, t0, 0.0), (-a - lo, t1, z1)
        return (a + lo, t0, 0.0), (a + hi, t1, z1)

    for side, half in (("-y", a), ("+y", a), ("-x", b), ("+x", b)):
        # outside the loop: a row of buildings past the corners; inside: a row up to the block's inner corners
        for where, t_lo, t_hi, sign in (("out", -half - 15.0, half + 15.0, 1.0), ("in", -half + d, half - d, -1.0)):
            t = t_lo + rng.uniform(0.0, 4.0)
            n = 0
            while t < t_hi - 3.0:
                width = min(rng.uniform(6.0, 16.0), t_hi - t)
                facade = d + rng.uniform(-1.0, 1.0)
                depth = rng.uniform(8.0, 12.0)
                lo, hi = along(side, t, t + width, sign * facade, sign * (facade + depth), rng.uniform(5.0, 18.0))
                boxes.append(SceneBox(f"building_{side}_{where}_{n}", lo, hi))
                t += width + rng.uniform(1.5, 5.0)
                n += 1
        # poles on both sides of the road, parked cars on the outer side
        for sign in (1.0, -1.0):
            t = -half + rng.uniform(2.0, 8.0)
            n = 0
            while t < half - 2.0:
                lo, hi = along(side, t, t + 0.3, sign * 4.5, sign * 4.8, rng.uniform(3.5, 6.0))
                boxes.append(SceneBox(f"pole_{side}_{'out' if sign > 0 else 'in'}_{n}", lo, hi))
                if sign > 0 and rng.random() < 0.5:
                    lo, hi = along(side, t + 2.0, t + 6.3, 2.6, 4.4, rng.uniform(1.4, 1.8))
                    boxes.append(SceneBox(f"car_{side}_{n}", lo, hi))
                t += rng.uniform(8.0, 15.0)
                n += 1
    return boxes


def boxes_of(config: SyntheticLogConfig) -> list[SceneBox]:
    """The scene of a log: :func:`scene_boxes` (``room``) or :func:`street_boxes` (``street``)."""
    if config.scene == "room":
        return scene_boxes(door_open=config.door_open, chair_moved=config.chair_moved)
    if config.scene == "street":
        return street_boxes(config.seed)
    raise SourceError(f"synthetic log: scene must be 'room' or 'street', got {config.scene!r}")


def build_scene(config: SyntheticLogConfig) -> tuple[o3d.t.geometry.RaycastingScene, set[int]]:
    """The scene of a log (:func:`boxes_of`) for ray casting, and the geometry ids of its glass (no depth reading)."""
    scene = o3d.t.geometry.RaycastingScene()
    glass_ids: set[int] = set()
    for box in boxes_of(config):
        size = np.subtract(box.max_m, box.min_m)
        mesh = o3d.geometry.TriangleMesh.create_box(*size)
        mesh.translate(box.min_m)
        gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        if box.glass:
            glass_ids.add(int(gid))
    return scene, glass_ids
