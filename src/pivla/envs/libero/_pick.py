"""The pick-and-place skill of the scripted LIBERO experts: pick object X, put it on / in target Y.

Targets are what LIBERO's BDDL goals name: another object (``(On bowl plate)``: LIBERO's On compares body
origins, within 3 cm, plus contact), an object's containing region (``(In soup basket_1_contain_region)``:
the container's centre), or a region of a fixture or of the table (``(On bowl flat_stove_1_cook_region)``,
``(In book desk_caddy_1_back_contain_region)``): for those a spot is searched inside the region, where the
object fits (its own footprint, turned if needed, with nothing under it higher than a gentle slope) and is
comfortably within reach. A spot partly under something (the back of a drawer, under the drawer above's
handle) is entered sideways from where the footprint is clear; inside an enclosure too low for the hand (the
microwave), the object is held by the part sticking out towards the opening (a mug's handle) and set down
as deep as the hand, kept in front of the ceiling, allows.

The grasp: concave objects (bowls, mugs, plates: a ray straight down through the centre lands near the
bottom) are grasped by the rim, the fingers closing radially; the rim angle (and how far inside the rim the
gripper axis sits) is chosen from a height map under both fingers, so that nothing (drawer walls, the
cookie box, the bowl's own walls) stands above the fingertips, and so that the arm can reach the grasp, the
lift and the release. Convex objects (cans, bottles, boxes) are grasped from the top across their narrowest
side; when the fingers would land on the object itself there (a moka pot's body is wider than the open
gripper), the height map finds a part they can close around (its lid knob).

Why one ~1000-line module: the grasp planners (``_plan_*``) and the phase machine (``step``, ``_goal``) share one
attempt's spot, footprint, height map and grasp, and a replan (``_replan``) runs the planners again from inside
the phases; the geometry that needs no skill state already lives in ``_geometry``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pivla.envs.libero._geometry import (
    COMFORT_REACH,
    FINGER_TIP,
    FINGER_TIP_HEIGHT,
    FINGER_UPPER,
    HAND_ABOVE_TIP,
    HAND_BACK,
    HAND_HALF_LENGTH,
    HAND_HALF_WIDTH,
    RAY_SPACING,
    TIP_BELOW_EEF,
    Scene,
    closing_yaw,
    gripper_rotation,
    highest_under,
    levelling,
    region_test,
    rotation_error,
    wrap,
    wrist_distance,
)
from pivla.envs.libero._skills import Command, ExpertConfig, PlanningError, Skill

# The wrist turns the gripper at most this far from neutral (the Panda's joint 7 allows about +-2.9 rad).
MAX_YAW = 2.6
SPOT_SPACING = 0.01  # candidate spots in a region are this far apart (m)
SLOPE_TOLERANCE = 0.025  # under a placed object's base, surfaces may lie this far below its rest (a sloping shelf)
FLAT_HEIGHT = 0.025  # a dish lower than this (m) and wider than the open gripper is grasped across a chord


@dataclass
class _Grasp:
    grasp: np.ndarray  # eef position at the grasp
    yaw: float
    lift_z: float  # eef height for the transfer
    close_below: float = 0.0  # while the fingers close, the eef is held this far (m) below the grasp


@dataclass
class _Spot:
    """Where an object goes in a region: its origin, how far the gripper turns it on the way, the surface it
    will rest on, and, for a spot under something, the horizontal direction out through the opening."""

    origin: np.ndarray
    turn: float
    support: float
    opening: np.ndarray | None
    outside: np.ndarray | None = None  # the origin just outside the opening, at the height it goes in
    ceiling: float = np.inf  # height of what hangs over the whole spot (an enclosure's ceiling)
    inner: np.ndarray | None = None  # the spot as planned, before a handle grasp moved it out (see _plan_handle)


class Target:
    """Where a held object goes (see the module docstring for the three kinds), or, with :meth:`clear_of`,
    anywhere on the table near it but out of a box (making room for a drawer that will open over it)."""

    def __init__(self, scene: Scene, name: str, goal: list[str]) -> None:
        rs = scene.rs
        self.scene = scene
        self.goal = goal
        self.into = goal[0].lower() == "in"
        key = name.removesuffix("_contain_region")
        entity = rs.objects_dict.get(key) if (self.into and name.endswith("_contain_region")) else None
        entity = entity or (rs.objects_dict.get(name) if not self.into else None)
        self.site: str | None = None
        self.exclude: tuple[np.ndarray, np.ndarray] | None = None
        if entity is not None:
            self.kind = "container" if self.into else "object"
            self.root = scene.root(entity.root_body)
        elif name in rs.object_sites_dict:
            self.kind = "region"
            self.site = name
            site = rs.object_sites_dict[name]
            self.size = np.asarray(site.size, dtype=np.float64)
        else:
            raise ValueError(f"goal target {name!r} is neither an object nor a region of the scene")
        self.spot: _Spot | None = None

    @classmethod
    def clear_of(cls, scene: Scene, obj: int, lo: np.ndarray, hi: np.ndarray) -> Target:
        """The table within 15 cm of object ``obj``, its whole footprint outside the xy box ``lo``-``hi``."""
        t = cls.__new__(cls)
        t.scene, t.goal, t.into, t.site, t.spot = scene, [], False, None, None
        t.kind = "region"
        t.exclude = (np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
        o_lo, o_hi = scene.aabb(obj)
        t.centre = np.array([*(o_lo[:2] + o_hi[:2]) / 2, o_lo[2]])
        t.radius = float(np.max(o_hi[:2] - o_lo[:2])) / 2
        return t

    def area(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(centre, half extents, lowest height, yaw) of the world box where the origin may go."""
        if self.exclude is not None:
            return self.centre, np.array([0.15, 0.15, 0.05]), float(self.centre[2]) - 0.02, 0.0
        pos, mat = self.scene.site(self.site)
        size = self.size
        yaw = float(np.arctan2(mat[1, 0], mat[0, 0]))
        if self.into:
            return pos, np.abs(mat) @ size, pos[2] - float(np.abs(mat @ size)[2]) - 0.01, yaw
        # The slab over the site's top face where LIBERO's "under" test holds, in world coordinates.
        deltas = np.array([[sx * size[0], sy * size[1], dz] for sx in (-1, 1) for sy in (-1, 1)
                           for dz in (size[2] - 0.005, size[2] + 0.10)])
        world = pos + deltas @ mat
        return world.mean(0), np.ptp(world, axis=0) / 2, float(world[:, 2].min()), yaw

    def accepts(self, origin: np.ndarray, margin: float) -> bool:
        """LIBERO's test of the goal region on an object origin, shrunk by ``margin`` (for a clear-of target:
        the footprint, ``radius`` around the origin, misses the excluded box)."""
        if self.exclude is not None:
            lo, hi = self.exclude
            return bool(np.any(origin[:2] < lo[:2] - self.radius) or np.any(origin[:2] > hi[:2] + self.radius))
        pos, mat = self.scene.site(self.site)
        margin = min(margin, 0.4 * float(min(self.size[0], self.size[1])))
        return region_test("in" if self.into else "on", pos, mat, self.size, origin, margin, 0.002)

    def holds(self) -> bool:
        return True if self.exclude is not None else self.scene.holds(self.goal)


class PickPlace(Skill):
    """Pick an object and put it on / in a target; plans the grasp again once above the object (objects may
    still be settling), and retries the grasp (up to ``max_attempts``) when the object did not come up."""

    PHASES = ("travel", "descend", "close", "slide", "lift", "transfer", "lower", "insert", "place", "press",
              "open", "withdraw", "retreat")
    PRECISE = frozenset({"descend", "close", "slide", "insert", "place", "press", "open", "withdraw"})

    def __init__(self, scene: Scene, config: ExpertConfig, obj_name: str, target: Target,
                 share: tuple[int, int] = (0, 1), miss: np.ndarray | None = None) -> None:
        """``share`` = (k, n): this is the k-th of n objects going to the same region (each gets its own part
        of it); ``miss``: execute the first grasp this far (xy, m) off the planned one (labels stay clean)."""
        super().__init__(scene, config)
        self.obj = scene.entity_root(obj_name)
        self.target = target
        self.share = share
        self.miss = miss
        self.failed: list[np.ndarray] = []  # xy of grasps that did not lift the object
        self.attempts = 0
        self.started = False
        self.plan: _Grasp | None = None

    # ---- targets -------------------------------------------------------------------------------------

    def _place_xy(self) -> np.ndarray:
        """Where the held object's reference point goes: LIBERO's On test compares body origins (within
        3 cm), so the target's origin for "on" goals; the container's centre for "in" goals; the planned spot
        in a region."""
        t = self.target
        if t.kind == "object":
            return self.scene.d.xpos[t.root][:2].copy()
        if t.kind == "container":
            t_lo, t_hi = self.scene.aabb(t.root)
            return (t_lo[:2] + t_hi[:2]) / 2
        return self._spot().origin[:2].copy()

    def _release_bottom(self) -> float:
        """Height of the held object's bottom at release: just above the target's top (or rim)."""
        cfg, t = self.config, self.target
        if t.kind == "region":
            return self._spot().support + cfg.place_above
        return float(self.scene.aabb(t.root)[1][2]) + (cfg.drop_above if t.kind == "container" else cfg.place_above)

    def _spot(self) -> _Spot:
        if self.target.spot is None:
            self.target.spot = self._plan_spot()
        return self.target.spot

    def _footprint(self, turn: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        """The object's footprint turned by ``turn``: points (relative to its origin, on a SPOT_SPACING grid
        over its box in its own frame) and the height of its underside above its bottom at each (inf where
        none of its parts is, so a handle or a spout may hang over something lower); its origin's height
        above its bottom; and its height. Heights are as it stands upright (it may be tilted in the hand)."""
        sc = self.scene
        origin = sc.d.xpos[self.obj]
        up = levelling(sc.d.xmat[self.obj].reshape(3, 3))
        yaw = sc.yaw(self.obj)
        c, s = np.cos(yaw), np.sin(yaw)
        to_own = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ up  # world offset -> upright own frame
        parts = [(sc.corners(np.array([g])) - origin) @ to_own.T for g in sc.geoms(self.obj)]
        allpts = np.concatenate(parts)
        bottom = float(allpts[:, 2].min())
        lo, hi = allpts[:, :2].min(0), allpts[:, :2].max(0)
        xs, ys = (np.linspace(lo[k], hi[k], max(2, int(np.ceil((hi[k] - lo[k]) / SPOT_SPACING)) + 1)) for k in (0, 1))
        grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        underside = np.full(len(grid), np.inf)
        for part in parts:
            p_lo, p_hi = part.min(0), part.max(0)
            inside = np.all((grid >= p_lo[:2] - SPOT_SPACING / 2) & (grid <= p_hi[:2] + SPOT_SPACING / 2), axis=1)
            underside[inside] = np.minimum(underside[inside], p_lo[2] - bottom)
        keep = np.isfinite(underside)
        a = yaw + turn
        ca, sa = np.cos(a), np.sin(a)
        world = grid[keep] @ np.array([[ca, sa], [-sa, ca]])
        return world, underside[keep], -bottom, float(allpts[:, 2].max() - bottom)

    def _plan_spot(self) -> _Spot:
        """A spot for the object's origin inside the target region: LIBERO's test holds there with a margin,
        the object fits (resting on the highest surface under its underside, with its base supported within
        a gentle slope, and nothing over it except, for an enclosure, a ceiling clear of it with an opening
        to come in by), preferring spots away from obstacles, near the region's centre and within comfortable
        reach, turning the object as little as possible. A region only an object held above its floor can be
        in (LIBERO tests the origin, and a book's is at its bottom) is accepted last: the goal then holds on
        the way down. Surfaces come from one height map of the region (rays every SPOT_SPACING)."""
        sc, cfg, t = self.scene, self.config, self.target
        centre, half, bottom_z, site_yaw = t.area()
        skip = {self.obj}
        obj_yaw = sc.yaw(self.obj)
        turns = sorted({round(wrap(site_yaw - obj_yaw + k * np.pi / 2), 6) for k in range(4)} | {0.0}, key=abs)
        plan_yaw = self.plan.yaw if self.plan is not None else 0.0
        turns = [a for a in turns if abs(plan_yaw + a) <= MAX_YAW and abs(a) <= np.pi / 2 + 1e-6]
        feet = {turn: self._footprint(turn) for turn in turns}
        _, _, above_bottom, height = feet[0.0]
        ticks = [np.arange(-half[k], half[k] + 1e-9, SPOT_SPACING) for k in (0, 1)]
        cells = centre[:2] + np.stack(np.meshgrid(*ticks), -1).reshape(-1, 2)
        k, n = self.share
        prefer = centre[:2].copy()  # spots near this point score higher
        if n > 1:  # the k-th of n objects for this region gets its k-th strip (far first), split across the
            # object's narrower side so that they fit side by side, and goes to the strip's outer edge
            foot = feet[0.0][0]
            axis = int(np.argmin(np.ptp(foot, axis=0)))
            edges = np.linspace(centre[axis] - half[axis], centre[axis] + half[axis], n + 1)
            mids = [np.where(np.arange(3) == axis, (edges[i] + edges[i + 1]) / 2, centre) for i in range(n)]
            strip = int(np.argsort([-wrist_distance(sc.shoulder, m) for m in mids])[k])
            cells = cells[(cells[:, axis] >= edges[strip]) & (cells[:, axis] <= edges[strip + 1])]
            outer = edges[strip] if abs(edges[strip] - centre[axis]) > abs(edges[strip + 1] - centre[axis]) \
                else edges[strip + 1]
            prefer[axis] = outer
        reach_out = max(float(np.max(np.linalg.norm(f[0], axis=1))) for f in feet.values()) + SPOT_SPACING
        z_from = bottom_z + above_bottom + height + 0.03
        lo_xy = cells.min(0) - reach_out
        shape = np.ceil((cells.max(0) + reach_out - lo_xy) / SPOT_SPACING).astype(int) + 1
        hx, hy = (lo_xy[k] + SPOT_SPACING * np.arange(shape[k]) for k in (0, 1))
        heights = np.array([[sc.ray_down(np.array([x, y]), z_from, skip)[0] for y in hy] for x in hx])
        # Seen from high up: where something hangs over the region (a cabinet's top, a drawer's handle, the
        # microwave's ceiling), the two maps differ.
        covered = np.array([[sc.ray_down(np.array([x, y]), 2.0, skip)[0] for y in hy] for x in hx]) > heights + 0.005
        # ... and the underside of what hangs over (the height a ray going up from the surface hits).
        cover_z = np.full(heights.shape, np.inf)
        for ix, iy in zip(*np.nonzero(covered)):
            base_z = heights[ix, iy] + 0.005
            cover_z[ix, iy] = base_z + sc.ray(np.array([hx[ix], hy[iy], base_z]), np.array([0.0, 0.0, 1.0]), skip)[0]
        self._cover_map = (lo_xy, covered)
        self._surface_map = (lo_xy, heights)
        opening: np.ndarray | None = None
        best: tuple[float, _Spot, np.ndarray] | None = None
        for turn in turns:
            foot, underside = feet[turn][0], feet[turn][1]
            idx = np.rint((cells[:, None, :] + foot[None, :, :] - lo_xy) / SPOT_SPACING).astype(int)
            zs = heights[idx[..., 0], idx[..., 1]]  # (cells, footprint points)
            rest = np.max(zs - underside, axis=1)  # the bottom's height once resting on the highest contact
            base = underside < 0.005
            fits = np.isfinite(rest) & np.all(zs[:, base] >= rest[:, None] - SLOPE_TOLERANCE, axis=1)
            # Where something hangs over part of the footprint (a drawer's handle above a drawer) or all of it
            # (the microwave's ceiling), the object must fit under it; it then comes in sideways from where the
            # footprint is clear (see ``_outside``).
            over = covered[idx[..., 0], idx[..., 1]]
            under = np.where(over, cover_z[idx[..., 0], idx[..., 1]], np.inf)
            fits &= np.all(under >= (rest + height + cfg.place_above + 0.005)[:, None], axis=1)
            if not fits.any():
                continue
            valid = np.zeros(len(cells), dtype=bool)
            spots: dict[int, tuple[_Spot, float]] = {}
            for i in np.flatnonzero(fits):
                xy, support = cells[i], float(rest[i])
                origin = np.array([*xy, support + above_bottom])
                penalty = 0.0
                if not t.accepts(origin, cfg.region_margin):
                    held = origin + [0.0, 0.0, cfg.place_above]
                    if not (t.into and t.accepts(held, cfg.region_margin)):
                        continue
                    penalty = 0.5
                way_in, ceiling = None, np.inf
                if over[i].all():  # inside an enclosure: the way in is its opening
                    if opening is None:
                        opening = self._opening(np.array([*xy, support + height / 2]), foot, skip)
                    if opening is None:
                        continue
                    way_in, ceiling = opening, float(under[i].min())
                elif over[i].any():  # partly under an overhang: in from the side away from it
                    away = xy - (xy + foot[over[i]]).mean(0)
                    way_in = away / max(float(np.linalg.norm(away)), 1e-9)
                valid[i] = True
                spots[i] = (_Spot(origin, turn, support, way_in, ceiling=ceiling), penalty)
            bad = cells[~valid]
            for i, (spot, penalty) in spots.items():
                xy = cells[i]
                clearance = float(np.min(np.linalg.norm(bad - xy, axis=1))) if len(bad) else 0.05
                stretch = wrist_distance(sc.shoulder, np.array([*xy, spot.support + height + 0.05]))
                score = (0.5 * min(clearance, 0.04) - 0.3 * float(np.linalg.norm(xy - prefer))
                         - 2.0 * max(stretch - COMFORT_REACH, 0.0) - 0.02 * abs(turn) - penalty)
                if best is None or score > best[0]:
                    best = (score, spot, foot, underside)
        if best is None:
            raise PlanningError(f"no spot in region {t.site or 'next to it'!r} fits {sc.body_name(self.obj)!r}")
        _, spot, foot, underside = best
        if spot.opening is not None:
            spot.outside = self._outside(spot, foot, underside)
        return spot

    def _opening(self, point: np.ndarray, foot: np.ndarray, skip: set[int]) -> np.ndarray | None:
        """The way out of an enclosure from ``point`` (inside it): of 16 horizontal directions whose run is
        free (rays at three heights), the one along which the footprint gets out from under the ceiling
        soonest (straight out of the microwave's front, not diagonally through a corner)."""
        lo_xy, covered = self._cover_map
        best, best_exit = None, np.inf
        for a in np.linspace(0, 2 * np.pi, 16, endpoint=False):
            u = np.array([np.cos(a), np.sin(a)])
            for dist in np.arange(0.0, 0.4, SPOT_SPACING):
                idx = np.rint((point[:2] + u * dist + foot - lo_xy) / SPOT_SPACING).astype(int)
                inside = np.all((idx >= 0) & (idx < covered.shape), axis=1)
                if not covered[idx[inside, 0], idx[inside, 1]].any():
                    break
            free = min(self.scene.ray(point + [0, 0, dz], np.array([*u, 0.0]), skip)[0] for dz in (-0.03, 0.0, 0.03))
            if free > dist + 0.05 and dist < best_exit:
                best, best_exit = u, dist
        return best

    # ---- grasp planning --------------------------------------------------------------------------------

    def _plan(self) -> _Grasp:
        """The grasp, and a transfer height that the hand clears too."""
        plan = self._plan_grasp()
        plan.lift_z = max(plan.lift_z, self._hand_sweep_z(plan))
        return plan

    def _plan_grasp(self) -> _Grasp:
        sc, cfg = self.scene, self.config
        centre, half, axes = sc.body_frame_extent(self.obj)
        lo, hi = sc.aabb(self.obj)
        spot = self._spot() if self.target.kind == "region" else None
        if spot is not None and np.isfinite(spot.ceiling) and \
                spot.support + cfg.place_above + (hi[2] - lo[2]) + HAND_ABOVE_TIP > spot.ceiling:
            handle = self._plan_handle(spot, lo, hi)
            if handle is None:
                raise PlanningError(f"no grasp of {sc.body_name(self.obj)!r} keeps the hand out of the enclosure")
            return handle
        z_top = hi[2]
        hit, root = sc.ray_down(centre[:2], z_top + 0.05)
        concave = root == self.obj and hit < z_top - 0.5 * (z_top - lo[2])
        if concave and z_top - lo[2] < FLAT_HEIGHT and float(np.min(half[:2])) > FINGER_TIP[0]:
            return self._plan_chord(half, lo, hi)
        if concave:
            return self._plan_rim(half, hi)
        # Convex object: grasp across the narrow side, fingertips a little below the top.
        narrow = axes[int(np.argmin(half[:2]))]
        floor_z = self._floor_below(lo, hi)
        tip_z = max(z_top - cfg.top_depth, floor_z + cfg.floor_clearance)
        grasp = np.array([centre[0], centre[1], tip_z + TIP_BELOW_EEF])
        plan = _Grasp(grasp, closing_yaw(narrow), grasp[2] + self._lift_above_grasp())
        if self._fingers_blocked(grasp, plan.yaw, tip_z):
            return self._plan_top(lo, hi, floor_z) or plan
        return plan

    def _plan_chord(self, half: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> _Grasp:
        """A grasp for a dish too flat for a rim grasp (a plate: its rim is a 5 mm lip sloping up 20 degrees,
        up which an inner finger slides): the fingers close across a chord near the edge, just outside it,
        on the lip's two ends (tilted 20 degrees from vertical: the squeeze stays within friction), the chord
        facing the target and within reach."""
        sc, cfg = self.scene, self.config
        origin = sc.d.xpos[self.obj][:2].copy()
        radius = float(np.mean(half[:2]))
        # The gripper axis as far out as keeps the open fingers' inner corners (a finger is 1.8 cm wide) 2 mm
        # off the edge: closing, they meet the lip's ends there.
        inner = FINGER_TIP[0]
        out = np.sqrt(max(radius**2 - inner**2, 0.0)) + FINGER_TIP[2] + 0.002
        to_place = self._place_xy() - origin
        lift_above = self._lift_above_grasp()
        best: tuple[float, _Grasp] | None = None
        for theta in np.linspace(0, 2 * np.pi, 24, endpoint=False):
            radial = np.array([np.cos(theta), np.sin(theta)])
            tangent = np.array([-radial[1], radial[0]])
            axis = origin + radial * out
            # The fingertips 4 mm under the lip's top where they meet it (lower, they pass under the raised
            # lip and close on nothing).
            ends = [origin + radial * (out - FINGER_TIP[2] - 0.006) + tangent * side * (inner - 0.006)
                    for side in (-1, 1)]
            lip = min(sc.ray_down(e, hi[2] + 0.02)[0] for e in ends)
            tip_z = max(lip - 0.004, self._floor_below(lo, hi) + cfg.floor_clearance)
            grasp = np.array([*axis, tip_z + TIP_BELOW_EEF])
            yaw = closing_yaw(tangent)
            if self._fingers_blocked(grasp, yaw, tip_z):
                continue
            stretch = max(wrist_distance(sc.shoulder, g) for g in (grasp, grasp + [0, 0, lift_above],
                                                                   grasp + [*to_place, 0.0]))
            score = 0.1 * float(radial @ to_place) / max(float(np.linalg.norm(to_place)), 1e-9) \
                - 2.0 * max(stretch - COMFORT_REACH, 0.0) - 0.004 * abs(yaw)
            if any(np.linalg.norm(grasp[:2] - f) < cfg.retry_distance for f in self.failed):
                score -= 0.5
            if best is None or score > best[0]:
                best = (score, _Grasp(grasp, yaw, grasp[2] + lift_above, cfg.chord_close_below))
        if best is None:
            raise PlanningError(f"no chord of {sc.body_name(self.obj)!r} is clear for the fingers")
        return best[1]

    def _plan_handle(self, spot: _Spot, lo: np.ndarray, hi: np.ndarray) -> _Grasp | None:
        """A grasp for a spot inside an enclosure whose ceiling is too low for the hand (10 cm tall pointing
        down, 7 cm pointing sideways, 20 cm across its fingers: the microwave is 14 cm tall): the gripper
        holds, from above, the part of the object that sticks out furthest towards the opening (a mug's
        handle), across it, and the spot moves out until the hand stays in front of the ceiling; what is
        left outside (the handle) the door pushes in when it closes. None when no part fits the fingers or
        the goal region cannot then be reached."""
        sc, cfg = self.scene, self.config
        u = spot.opening
        origin = sc.d.xpos[self.obj]
        parts = [sc.corners(np.array([g])) for g in sc.geoms(self.obj)]
        part = max(parts, key=lambda p: float(np.max((p[:, :2] - origin[:2]) @ u)))
        lateral = np.array([-u[1], u[0]])
        if np.ptp(part[:, :2] @ lateral) > 2 * (FINGER_TIP[0] - 0.012):
            return None
        centre = (part.min(0) + part.max(0)) / 2
        # The fingers across the part's outer end (5 mm in from it): the further out, the deeper the object
        # can go with the hand still in front of the ceiling.
        outer = float(np.max((part[:, :2] - origin[:2]) @ u))
        xy = centre[:2] + u * (outer - 0.005 - float((centre[:2] - origin[:2]) @ u))
        floor_z = self._floor_below(lo, hi)
        tip_z = max(part[:, 2].max() - cfg.top_depth, part[:, 2].min() + 0.005, floor_z + cfg.floor_clearance)
        grasp = np.array([xy[0], xy[1], tip_z + TIP_BELOW_EEF])
        # Of the two yaws closing across the part, the one turning the hand's shallow side (3.0 cm from the
        # axis, against 3.85 cm) towards the enclosure.
        yaw = closing_yaw(lateral)
        if np.array([np.cos(yaw), np.sin(yaw)]) @ u < 0:
            yaw = wrap(yaw + np.pi)
        if self._fingers_blocked(grasp, yaw, tip_z):
            return None
        # Out along the opening until the hand (about the grasp, in the object's pose at the spot) is clear
        # of the ceiling, with 2 mm to spare; the origin must still pass LIBERO's test and rest on the floor.
        rel = grasp[:2] - origin[:2]
        x_e, y_e = np.array([np.cos(yaw), np.sin(yaw)]), np.array([np.sin(yaw), -np.cos(yaw)])
        hand = np.array([x_e * (-HAND_BACK - 0.002) + y_e * b
                         for b in np.linspace(-HAND_HALF_LENGTH, HAND_HALF_LENGTH, 9)])
        hand_bottom = spot.support + cfg.place_above + (tip_z - lo[2]) + HAND_ABOVE_TIP
        best: tuple[float, np.ndarray] | None = None
        if spot.inner is None:
            spot.inner = spot.origin.copy()
        for side in sorted(np.arange(-0.1, 0.1001, 0.01), key=abs):  # also sideways, clear of what sticks out
            for shift in np.arange(0.0, 0.15, 0.002):
                xy = spot.inner[:2] + u * shift + lateral * side
                if any(sc.ray_down(xy + rel + h, 2.0, {self.obj})[0] > hand_bottom for h in hand):
                    continue
                moved = np.array([*xy, spot.origin[2]])
                if self.target.accepts(moved, 0.001) and self._rests_at(xy, spot) and \
                        (best is None or shift < best[0] - 1e-9):
                    best = (shift, moved)
                break
        if best is None:
            return None
        spot.origin = best[1]
        return _Grasp(grasp, yaw, grasp[2] + self._lift_above_grasp())

    def _rests_at(self, xy: np.ndarray, spot: _Spot) -> bool:
        """Whether the object's base, at ``xy``, rests on the surface the spot was planned on."""
        foot, underside, _, _ = self._footprint(spot.turn)
        lo_xy, heights = self._surface_map
        idx = np.rint((xy + foot - lo_xy) / SPOT_SPACING).astype(int)
        if not np.all((idx >= 0) & (idx < heights.shape)):
            return False
        zs = heights[idx[:, 0], idx[:, 1]]
        base = underside < 0.005
        return bool(np.all(zs[base] >= spot.support - SLOPE_TOLERANCE)
                    and np.max(zs - underside) < spot.support + 0.005)

    def _fingers_blocked(self, grasp: np.ndarray, yaw: float, tip_z: float) -> bool:
        """Whether either open finger would land on something (the object included) above ``tip_z``."""
        grid_xy, grid_z = self._heightmap(grasp[:2], FINGER_UPPER[1] + 0.01, tip_z + 0.15)
        closing = np.array([-np.sin(yaw), np.cos(yaw)])
        rel = grid_xy - grasp[:2]
        along, across = np.abs(rel @ closing), np.abs(rel @ np.array([closing[1], -closing[0]]))
        under = max(highest_under(grid_z, along, across, FINGER_TIP, 0.0),
                    highest_under(grid_z, along, across, FINGER_UPPER, 0.0) - FINGER_TIP_HEIGHT)
        return under > tip_z

    def _plan_top(self, lo: np.ndarray, hi: np.ndarray, floor_z: float) -> _Grasp | None:
        """A top grasp where both fingers can go down beside some part of the object that stands between them
        (deepest pinch first, then nearest the object's centre, the hand clear of what stands around); None
        when there is none."""
        sc, cfg = self.scene, self.config
        origin = sc.d.xpos[self.obj][:2]
        span = float(np.max(hi[:2] - lo[:2])) / 2
        grid_xy, grid_z = self._heightmap((lo[:2] + hi[:2]) / 2, span + FINGER_UPPER[1] + cfg.finger_clearance,
                                          hi[2] + 0.1)
        roots = np.array([sc.ray_down(xy, hi[2] + 0.1)[1] for xy in grid_xy])
        over_xy, over_z = self._heightmap((lo[:2] + hi[:2]) / 2, span + HAND_HALF_LENGTH, 2.0, 2 * RAY_SPACING)
        best: tuple[float, _Grasp] | None = None
        centres = grid_xy[(roots == self.obj)][::2]
        for c in centres:
            for yaw in np.linspace(-np.pi / 2, np.pi / 2, 12, endpoint=False):
                closing = np.array([-np.sin(yaw), np.cos(yaw)])
                rel = grid_xy - c
                along, across = np.abs(rel @ closing), np.abs(rel @ np.array([closing[1], -closing[0]]))
                under = max(highest_under(grid_z, along, across, FINGER_TIP, cfg.finger_clearance),
                            highest_under(grid_z, along, across, FINGER_UPPER, cfg.finger_clearance)
                            - FINGER_TIP_HEIGHT)
                between = (along < FINGER_TIP[0] - 0.004) & (across < FINGER_TIP[2]) & (roots == self.obj)
                if not between.any():
                    continue
                top = float(grid_z[between].max())
                tip_z = max(top - cfg.top_depth, under + 0.004, floor_z + cfg.floor_clearance)
                depth = top - tip_z
                if depth < cfg.min_pinch:
                    continue
                score = min(depth, cfg.top_depth) - 0.5 * float(np.linalg.norm(c - origin)) - 0.004 * abs(yaw)
                if self._hand_blocked(over_xy, over_z, c, yaw, tip_z):
                    score -= 0.5
                if best is None or score > best[0]:
                    grasp = np.array([c[0], c[1], tip_z + TIP_BELOW_EEF])
                    best = (score, _Grasp(grasp, float(yaw), 0.0))
        if best is None:
            return None
        plan = best[1]
        plan.lift_z = plan.grasp[2] + self._lift_above_grasp()
        return plan

    def _floor_below(self, lo: np.ndarray, hi: np.ndarray) -> float:
        """Height of the surface the object rests on (rays just outside its footprint)."""
        sc = self.scene
        zs = []
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            xy = (lo[:2] + hi[:2]) / 2 + np.array([dx, dy]) * ((hi[:2] - lo[:2]) / 2 + 0.01)
            z, _ = sc.ray_down(xy, hi[2] + 0.01)
            zs.append(z)
        return max(min(zs), lo[2]) if np.isfinite(min(zs)) else lo[2]

    def _plan_rim(self, half: np.ndarray, hi: np.ndarray) -> _Grasp:
        """Pick the rim point where both fingers can go deepest: nothing (the bowl itself included) under them,
        with ``finger_clearance`` to spare sideways.

        The gripper axis may also sit inside the rim (``rim_offsets``): closing then slides the bowl that far
        towards the axis, and the outer finger keeps clear of a wall close to the bowl (a drawer's sides).
        Grasps are also scored by reach: the grasp, the lift above it and the release over the target
        should lie within COMFORT_REACH (a bowl in the drawer is at the edge of the arm's reach). Grasps
        whose fingers cannot get well below the rim rank even below a retry next to a failed grasp. For a
        spot inside an enclosure, the grasp faces its opening (the hand, 20 cm along the closing axis, then
        stays in line with the way in)."""
        sc, cfg = self.scene, self.config
        radius = float(np.mean(half[:2]))
        origin = sc.d.xpos[self.obj][:2].copy()
        lift_above = self._lift_above_grasp()
        # Where the eef will hold the object over the target, relative to the grasp: it must be reachable too.
        to_place = np.array([*(self._place_xy() - origin), self._release_bottom() - sc.aabb(self.obj)[0][2]])
        spot = self.target.spot if self.target.kind == "region" else None
        grid_xy, grid_z = self._heightmap(origin, radius + FINGER_UPPER[1] + cfg.finger_clearance, hi[2] + 0.1)
        over_xy, over_z = self._heightmap(origin, radius + HAND_HALF_LENGTH, 2.0, 2 * RAY_SPACING)
        best: tuple[float, float, np.ndarray] | None = None
        for theta in np.linspace(0, 2 * np.pi, 24, endpoint=False):
            radial = np.array([np.cos(theta), np.sin(theta)])
            tangent = np.array([-radial[1], radial[0]])
            # The rim top is the bowl's highest point along this radial line (robust to a tilted bowl).
            rim_top, rim_xy = -np.inf, None
            for r in np.linspace(0.3 * radius, 1.2 * radius, 19):
                xy = origin + radial * r
                z, root = sc.ray_down(xy, hi[2] + 0.05)
                if root == self.obj and z > rim_top:
                    rim_top, rim_xy = z, xy
            if rim_xy is None:
                continue
            yaw = closing_yaw(radial)
            for offset in cfg.rim_offsets:
                axis_xy = rim_xy - radial * offset
                # Highest surface of anything under either finger (the bowl's own walls count too), as seen
                # by the tip; the wider part above it may pass over what is lower than FINGER_TIP_HEIGHT.
                rel = grid_xy - axis_xy
                along, across = np.abs(rel @ radial), np.abs(rel @ tangent)
                under = max(highest_under(grid_z, along, across, FINGER_TIP, cfg.finger_clearance),
                            highest_under(grid_z, along, across, FINGER_UPPER, cfg.finger_clearance)
                            - FINGER_TIP_HEIGHT)
                tip_z = max(rim_top - cfg.rim_depth, under + 0.004)
                depth = rim_top - tip_z
                margin = tip_z - under  # room under the fingers: prefer grasps away from walls and neighbours
                score = min(depth, cfg.rim_depth) + 0.5 * min(margin, 0.03) - 0.004 * abs(yaw) - 0.5 * offset
                grasp = np.array([*axis_xy, tip_z + TIP_BELOW_EEF])
                stretch = max(wrist_distance(sc.shoulder, g)
                              for g in (grasp, grasp + [0, 0, lift_above], grasp + to_place))
                score -= 2.0 * max(stretch - COMFORT_REACH, 0.0)
                if depth < cfg.rim_depth / 2:
                    score -= 1.0
                if self._hand_blocked(over_xy, over_z, axis_xy, yaw, tip_z):
                    score -= 2.0
                if any(np.linalg.norm(grasp[:2] - f) < cfg.retry_distance for f in self.failed):
                    score -= 0.5
                if spot is not None:
                    c, s = np.cos(spot.turn), np.sin(spot.turn)
                    turned = np.array([c * radial[0] - s * radial[1], s * radial[0] + c * radial[1]])
                    if spot.opening is not None:  # the hand, 20 cm along the closing axis, in line with the way in
                        score += 0.5 * float(turned @ spot.opening) - (1.0 if turned @ spot.opening < 0.94 else 0.0)
                    if not self._fingers_fit_at(spot, grasp[:2] - origin, turned, tip_z - sc.aabb(self.obj)[0][2]):
                        score -= 1.0
                if best is None or score > best[0]:
                    best = (score, yaw, grasp)
        if best is None:
            raise PlanningError("no rim point of the bowl is visible from above")
        _, yaw, grasp = best
        return _Grasp(grasp, yaw, grasp[2] + lift_above)

    def _fingers_fit_at(self, spot: _Spot, axis_rel: np.ndarray, radial: np.ndarray, tip_above_bottom: float) -> bool:
        """Whether the outer finger of a rim grasp (closed on the wall: from the gripper axis outwards by a
        finger's thickness) clears what is at the spot (a drawer's front beside the bowl), once the object is
        there at its release height. ``axis_rel``: the gripper axis from the object's origin now (xy)."""
        c, s = np.cos(spot.turn), np.sin(spot.turn)
        axis = spot.origin[:2] + np.array([c * axis_rel[0] - s * axis_rel[1], s * axis_rel[0] + c * axis_rel[1]])
        tangent = np.array([-radial[1], radial[0]])
        pts = np.array([axis + radial * a + tangent * b for a in np.linspace(0.0, 0.018, 4)
                        for b in (-FINGER_TIP[2], 0.0, FINGER_TIP[2])])
        lo_xy, heights = self._surface_map
        idx = np.rint((pts - lo_xy) / SPOT_SPACING).astype(int)
        inside = np.all((idx >= 0) & (idx < heights.shape), axis=1)
        tip_z = spot.support + self.config.place_above + tip_above_bottom
        return bool(np.all(heights[idx[inside, 0], idx[inside, 1]] < tip_z - 0.002))

    @staticmethod
    def _hand_blocked(over_xy: np.ndarray, over_z: np.ndarray, axis_xy: np.ndarray, yaw: float,
                      tip_z: float) -> bool:
        """Whether anything seen from above (``over_*``, a height map from high up) stands above the hand's
        lowest face over its footprint, with the fingertips at ``tip_z``: a drawer pulled out over the object."""
        closing = np.array([-np.sin(yaw), np.cos(yaw)])
        rel = over_xy - axis_xy
        inside = (np.abs(rel @ closing) < HAND_HALF_LENGTH) & (np.abs(rel @ np.array([closing[1], -closing[0]]))
                                                              < HAND_HALF_WIDTH)
        return bool(np.max(over_z, initial=-np.inf, where=inside) > tip_z + HAND_ABOVE_TIP)

    def _heightmap(self, centre: np.ndarray, half: float, z_from: float,
                   spacing: float = RAY_SPACING) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 2) of a square grid around ``centre`` and the height of the first surface under each."""
        ticks = np.arange(-half, half + 1e-9, spacing)
        grid_xy = centre + np.stack(np.meshgrid(ticks, ticks), -1).reshape(-1, 2)
        return grid_xy, np.array([self.scene.ray_down(xy, z_from)[0] for xy in grid_xy])

    def _lift_above_grasp(self) -> float:
        """How far the eef rises from the grasp so that the held object's bottom clears every body between
        pick and place (for a spot inside an enclosure: between pick and the point outside its opening)."""
        sc, t = self.scene, self.target
        lo, hi = sc.aabb(self.obj)
        start = (lo[:2] + hi[:2]) / 2
        if t.kind == "region":
            spot = self._spot()
            end = spot.origin[:2] if spot.outside is None else spot.outside[:2]
            top = max(spot.support, self._clear_height(start, end, self.obj))
        else:
            t_lo, t_hi = sc.aabb(t.root)
            top = max(t_hi[2], self._clear_height(start, (t_lo[:2] + t_hi[:2]) / 2, self.obj))
        return top + self.config.lift_clearance - lo[2]

    def _hand_sweep_z(self, p: _Grasp) -> float:
        """The lowest transfer height of the eef at which the hand (20 cm long along the closing axis, so it
        reaches well past the held object's sides) passes over everything on its way from the grasp to the
        release: a rim grasp on a bowl next to a cabinet otherwise carries the hand into the cabinet's side,
        which tilts the gripper and throws the arm out to its elbow limit."""
        sc, t = self.scene, self.target
        end = self._place_xy()
        spot = t.spot if t.kind == "region" else None
        if spot is not None and spot.outside is not None:
            end = spot.outside[:2]
        a = p.grasp[:2]
        b = end - (sc.d.xpos[self.obj][:2] - a)  # the eef over the release, the object held as grasped
        turn = spot.turn if spot is not None else 0.0
        along = np.arange(-HAND_HALF_LENGTH, HAND_HALF_LENGTH + 1e-9, 0.01)
        across = np.arange(-HAND_BACK, HAND_HALF_WIDTH + 1e-9, 0.01)
        box = np.stack(np.meshgrid(along, across), -1).reshape(-1, 2)  # (closing axis, eef x) offsets
        top = -np.inf
        for f in np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / 0.01) + 1)):
            yaw = p.yaw + f * turn
            closing, forward = np.array([-np.sin(yaw), np.cos(yaw)]), np.array([np.cos(yaw), np.sin(yaw)])
            for xy in a + f * (b - a) + box[:, :1] * closing + box[:, 1:] * forward:
                top = max(top, sc.ray_down(xy, 2.0, {self.obj})[0])
        return top + self.config.hand_clearance - (HAND_ABOVE_TIP - TIP_BELOW_EEF)

    def _outside(self, spot: _Spot, foot: np.ndarray, underside: np.ndarray) -> np.ndarray:
        """The object's origin where it goes down before coming in sideways, at the height it comes in.

        Out of an enclosure: moved out along the way in until no part of its footprint is under anything, plus
        ``insert_standoff``. From under a mere overhang (a bowl's rim under the rail above a half-open drawer):
        where its footprint is under nothing and over nothing taller than the height it comes in at (the
        drawer's front wall a few centimetres further out), searched in 2-mm steps, in the middle of the first
        such stretch but at most 1 cm into it; with no such point, 1 cm past the first one clear of the
        overhang."""
        lo_xy, covered = self._cover_map
        _, heights = self._surface_map
        in_height = spot.support + self.config.place_above - 0.003

        def at(dist: float) -> tuple[np.ndarray, np.ndarray, bool]:
            """Origin xy, which footprint points are under something, whether all are over low ground."""
            xy = spot.origin[:2] + spot.opening * dist
            idx = np.rint((xy + foot - lo_xy) / SPOT_SPACING).astype(int)
            inside = np.all((idx >= 0) & (idx < covered.shape), axis=1)
            idx = np.clip(idx, 0, np.array(covered.shape) - 1)
            over = covered[idx[:, 0], idx[:, 1]] & inside
            low = inside & (heights[idx[:, 0], idx[:, 1]] - underside <= in_height)
            return xy, over, bool(low.all())

        if at(0.0)[1].all():  # an enclosure
            first = next((d for d in np.arange(0.0, 0.4, SPOT_SPACING) if not at(d)[1].any()), 0.4)
            xy = at(first)[0] + spot.opening * self.config.insert_standoff
            return np.array([*xy, spot.origin[2] + self.config.place_above])
        dists = np.arange(0.0, 0.4, SPOT_SPACING / 5)
        clear, fits = [], []
        for d in dists:
            _, over, low = at(d)
            clear.append(not over.any())
            fits.append(clear[-1] and low)
        if any(fits):
            first = last = fits.index(True)
            while last + 1 < len(fits) and fits[last + 1]:
                last += 1
            xy = at(min(dists[first] + 0.01, (dists[first] + dists[last]) / 2))[0]
        else:
            xy = at((dists[clear.index(True)] if any(clear) else 0.4) + 0.01)[0]
        return np.array([*xy, spot.origin[2] + self.config.place_above])

    def _clear_height(self, a: np.ndarray, b: np.ndarray, ignore: int) -> float:
        """Highest surface (other than body ``ignore``) within 5 cm of the segment a -> b (xy), sampled densely
        enough along it not to miss a thin wall across it (a drawer's front)."""
        sc = self.scene
        top = -np.inf
        for s in np.linspace(0, 1, max(12, int(np.linalg.norm(b - a) / RAY_SPACING) + 2)):
            xy = a + (b - a) * s
            for off in ((0, 0), (0.05, 0), (-0.05, 0), (0, 0.05), (0, -0.05)):
                z, root = sc.ray_down(xy + np.array(off), 2.0)
                if root != ignore:
                    top = max(top, z)
        return top

    # ---- acting ---------------------------------------------------------------------------------------

    def _start_attempt(self, ee: np.ndarray) -> None:
        self.attempts += 1
        if self.target.kind == "region":
            self.target.spot = None  # planned again: the scene may have changed since the last attempt
        self.plan = None
        self.plan = self._plan()
        above = self.plan.grasp[2] + self.config.approach_above
        self.travel_z = max(above, self._clear_height(ee[:2], self.plan.grasp[:2], -1) + self.config.travel_clearance)
        self.start_xy = ee[:2].copy()  # the eef rises here first when it starts low
        self.obj_bottom0 = self.scene.aabb(self.obj)[0][2]
        self.replans = 0
        self.closest, self.stall = np.inf, 0  # progress of the descent
        self.slide: np.ndarray | None = None  # horizontal move of the held object before lifting it
        self.held: np.ndarray | None = None  # object origin relative to the eef when the transfer began
        self.press_from: float | None = None
        self.phase = 0
        self.phase_steps = 0
        self.aim = self.miss if (self.attempts == 1 and self.miss is not None) else None

    def _held_offset(self, ee: np.ndarray) -> np.ndarray:
        """The held object's reference point (xy) and bottom (z) relative to the eef; the object may have
        shifted or tilted in the hand. For "on" goals and regions the reference point is where the object's
        origin will be once it has tipped upright about its lowest point after release."""
        sc = self.scene
        pts = sc.corners(sc.geoms(self.obj))
        lowest = pts[int(np.argmin(pts[:, 2]))]
        if self.target.kind == "container":
            ref = (pts[:, :2].min(0) + pts[:, :2].max(0)) / 2
        else:
            ref = (lowest + levelling(sc.d.xmat[self.obj].reshape(3, 3)) @ (sc.d.xpos[self.obj] - lowest))[:2]
        return np.array([*ref, lowest[2]]) - ee

    def step(self, ee: np.ndarray, rot: np.ndarray) -> Command | None:
        if not self.started:
            self.started = True
            self._start_attempt(ee)
        cfg = self.config
        while self.phase < len(self.PHASES):
            phase = self.PHASES[self.phase]
            command, finished = self._goal(phase, ee, rot)
            if not finished:
                self.phase_steps += 1
                return command
            if phase == "travel" and self._replan():
                continue
            failed = (
                (phase == "lift" and not self._lifted())
                or (phase == "close" and self.aim is not None)
                or (phase == "descend" and self.stall >= cfg.stall_steps and self.closest > cfg.pos_tol)
                or (phase in ("transfer", "lower", "insert", "place") and self._dropped(ee))
            )
            if failed and self.attempts < cfg.max_attempts:
                if self.aim is None:
                    self.failed.append(self.plan.grasp[:2].copy())
                self._start_attempt(ee)
                continue
            self._next_phase()
        return None

    def _replan(self) -> bool:
        """Plan the grasp again just before going down (objects may still be settling when the episode
        starts, e.g. a bowl sliding off a ramekin); True when the new grasp must be travelled to first, so
        that the gripper turns above the object rather than next to it."""
        old, self.plan = self.plan, self._plan()
        # Yaws pi apart close the fingers along the same line: keep the one nearest the current target, or
        # a grasp across a square-ish object may flip and make the gripper turn half a circle going down.
        turn_by = (self.plan.yaw - old.yaw + np.pi / 2) % np.pi - np.pi / 2
        self.plan.yaw = old.yaw + turn_by
        turn = abs(turn_by)
        shift = float(np.linalg.norm(self.plan.grasp[:2] - old.grasp[:2]))
        cfg = self.config
        if (shift > cfg.replan_shift or turn > cfg.replan_turn) and self.replans < cfg.max_replans:
            self.replans += 1
            self.phase_steps = 0
            return True
        return False

    def _at_rest(self) -> bool:
        lin, ang = self.scene.speed(self.obj)
        return lin < self.config.rest_speed and ang < self.config.rest_spin

    def _overhang_escape(self) -> np.ndarray:
        """Horizontal move (xy) that takes the object out from under anything above it, so that it can be
        lifted (a bowl at the back of an open drawer is partly under the cabinet's top); zero when free."""
        sc = self.scene
        lo, hi = sc.aabb(self.obj)
        ticks = [np.arange(lo[k], hi[k] + 1e-9, 0.005) for k in (0, 1)]
        grid = [np.array([x, y]) for x in ticks[0] for y in ticks[1]]
        footprint = np.array([xy for xy in grid if sc.ray_down(xy, hi[2] + 0.001)[1] == self.obj])
        covered = np.array([xy for xy in footprint if sc.ray_down(xy, 2.0)[1] != self.obj])  # something above
        if len(covered) == 0:
            return np.zeros(2)
        centre = footprint.mean(0)
        away = centre - covered.mean(0)
        away /= np.linalg.norm(away)
        # Until the object's rearmost point passes the overhang's frontmost covered point, plus a margin.
        return away * (float(np.max(covered @ away) - np.min(footprint @ away)) + self.config.overhang_margin)

    def _lifted(self) -> bool:
        return self.scene.aabb(self.obj)[0][2] > self.obj_bottom0 + 0.02

    def _dropped(self, ee: np.ndarray) -> bool:
        """Whether the held object has left the hand since the transfer began (it moved that far from the eef)."""
        held = self.scene.d.xpos[self.obj] - ee
        if self.held is None:
            self.held = held
        return bool(np.linalg.norm(held - self.held) > self.config.drop_distance)

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        """(command, whether the phase is finished). Every goal is within the arm's reach."""
        cfg, p, reach = self.config, self.plan, self.reach
        timed_out = self.phase_steps >= cfg.waypoint_timeout
        spot = self.target.spot if self.target.kind == "region" else None
        enclosed = spot is not None and spot.opening is not None
        carrying = ("transfer", "lower", "insert", "place", "press", "open", "withdraw")
        target_rot = gripper_rotation(p.yaw + (spot.turn if spot is not None and phase in carrying else 0.0))
        oriented = np.linalg.norm(rotation_error(target_rot, rot)) < cfg.ori_tol
        if phase == "travel":
            rise = reach(np.array([*self.start_xy, self.travel_z]))
            if ee[2] < rise[2] - 0.02 and np.linalg.norm(ee[:2] - p.grasp[:2]) > 0.02 and not timed_out:
                return Command(rise, target_rot, -1.0), False
            goal = reach(np.array([*p.grasp[:2], self.travel_z]))
            if self.aim is not None:  # a deliberate miss: executed beside the object, labelled onto it
                aim = reach(goal + [*self.aim, 0.0])
                return Command(goal, target_rot, -1.0, aim), self._arrived(aim, ee, oriented, cfg.pos_tol, timed_out)
            if not self._at_rest() and not timed_out:
                return Command(goal, target_rot, -1.0), False
            return Command(goal, target_rot, -1.0), self._arrived(goal, ee, oriented, cfg.pos_tol, timed_out)
        if phase == "descend":
            goal = reach(p.grasp)
            if self.aim is not None:
                aim = reach(self._missed_grasp())
                return Command(goal, target_rot, -1.0, aim), self._arrived(aim, ee, True, cfg.pos_tol, timed_out)
            dist = float(np.linalg.norm(goal - ee))
            if dist < self.closest - 0.001 or dist < cfg.pos_tol:
                self.closest, self.stall = min(dist, self.closest), 0
            else:
                self.stall += 1
            if self.stall >= cfg.stall_steps:
                return Command(goal, target_rot, -1.0), True
            return Command(goal, target_rot, -1.0), self._arrived(goal, ee, oriented, cfg.grasp_tol, timed_out)
        if phase in ("close", "open"):
            steps, grip = (cfg.close_steps, 1.0) if phase == "close" else (cfg.open_steps, -1.0)
            if phase == "close" and self.aim is not None:  # executed: closing on nothing; labelled: still open
                return Command(reach(p.grasp), target_rot, -1.0, ee.copy(), 1.0), self.phase_steps >= steps
            if phase == "open" and self.phase_steps == 0:
                self.release_ee = ee.copy()
            if phase == "close" and p.close_below:
                return Command(reach(p.grasp - [0.0, 0.0, p.close_below]), target_rot, grip), self.phase_steps >= steps
            return Command(None, None, grip), self.phase_steps >= steps
        if phase == "slide":
            if self.slide is None:
                self.slide = self._overhang_escape()
            if not self.slide.any():
                return Command(None, None, 1.0), True
            goal = reach(np.array([*(p.grasp[:2] + self.slide), p.grasp[2]]))
            return Command(goal, target_rot, 1.0), self._arrived(goal, ee, True, cfg.pos_tol, timed_out)
        if phase == "lift":
            goal = reach(np.array([*(p.grasp[:2] + self.slide), p.lift_z]))
            return Command(goal, target_rot, 1.0), self._arrived(goal, ee, True, cfg.pos_tol, timed_out)
        if phase in ("transfer", "lower", "insert", "place") and self._dropped(ee):
            return Command(None, None, 1.0), True
        if phase in ("lower", "insert", "withdraw") and not enclosed:
            return Command(None, None, 1.0 if phase != "withdraw" else -1.0), True
        if phase in ("transfer", "lower", "insert", "place"):
            off = self._held_offset(ee)
            xy = spot.outside[:2] if enclosed and phase in ("transfer", "lower") else self._place_xy()
            z = p.lift_z if phase == "transfer" else self._release_bottom() - off[2]
            goal = reach(np.array([*(xy - off[:2]), z]))
            if phase == "transfer":
                tol = cfg.transfer_tol if spot is None or spot.opening is None else cfg.pos_tol
                return Command(goal, target_rot, 1.0), self._arrived(goal, ee, oriented or not enclosed, tol, timed_out)
            # Going down or in with the object: a stall (it sits on something) ends the phase early.
            stalled = spot is not None and self._stalled(float(np.linalg.norm(goal - ee)))
            return Command(goal, target_rot, 1.0), stalled or self._arrived(goal, ee, oriented or spot is None,
                                                                            cfg.pos_tol, timed_out)
        if phase == "press":
            # A region goal that does not hold yet at the release height (it needs contact, or the origin
            # lower): keep lowering slowly until it holds or the object stops going down.
            if spot is None or self.target.holds():
                return Command(None, None, 1.0), True
            if self.press_from is None:
                self.press_from = float(ee[2])
            floor = self.press_from - cfg.press_depth
            goal = reach(np.array([*ee[:2], max(ee[2] - 0.01, floor)]))
            stopped = self.phase_steps > 3 and self.scene.speed(self.obj)[0] < 0.005
            return Command(goal, target_rot, 1.0), stopped or timed_out or ee[2] < floor + 0.002
        if phase == "withdraw":  # back out through the opening, at the height the object was let go
            out = spot.outside[:2] - spot.origin[:2]
            goal = reach(self.release_ee + [*out, 0.0])
            return Command(goal, target_rot, -1.0), self._arrived(goal, ee, True, cfg.pos_tol, timed_out)
        # Retreat: up, clear of the object just let go (the next subgoal's travel rises further if it must).
        goal = reach(np.array([ee[0], ee[1], min(p.lift_z, self.release_ee[2] + 0.08)]))
        return Command(goal, target_rot, -1.0), self._arrived(goal, ee, True, 0.02, timed_out)

    def _stalled(self, dist: float) -> bool:
        """Whether the distance to the current waypoint has not shrunk by 1 mm for ``stall_steps`` steps."""
        if self.phase_steps == 0:
            self.closest, self.stall = np.inf, 0
        if dist < self.closest - 0.001:
            self.closest, self.stall = dist, 0
        else:
            self.stall += 1
        return self.stall >= self.config.stall_steps

    @staticmethod
    def _arrived(goal: np.ndarray, ee: np.ndarray, oriented: bool, tol: float, timed_out: bool) -> bool:
        return bool(np.linalg.norm(goal - ee) < tol and oriented) or timed_out

    def _missed_grasp(self) -> np.ndarray:
        """Where a deliberately missed grasp goes down: beside the object, no lower than the planned grasp
        and clear of whatever is there."""
        xy = self.plan.grasp[:2] + self.aim
        floor, _ = self.scene.ray_down(xy, self.plan.grasp[2] + 0.1)
        return np.array([*xy, max(self.plan.grasp[2], floor + 0.01 + TIP_BELOW_EEF)])


def miss_direction(scene: Scene, obj: int, rng: np.random.Generator, distance: float) -> np.ndarray:
    """A horizontal offset of ``distance`` from the object's centre towards free table (of 8 directions, drawn
    in random order, the first whose spot has nothing higher than 1 cm above the surface next to the object)."""
    lo, hi = scene.aabb(obj)
    centre = (lo[:2] + hi[:2]) / 2
    floor = lo[2]
    angles = rng.permutation(np.linspace(0, 2 * np.pi, 8, endpoint=False)) + rng.uniform(0, np.pi / 4)
    for a in angles:
        off = distance * np.array([np.cos(a), np.sin(a)])
        z, root = scene.ray_down(centre + off, hi[2] + 0.1)
        if root != obj and z < floor + 0.01:
            return off
    a = angles[0]
    return distance * np.array([np.cos(a), np.sin(a)])

