"""Automated data collection from the camera alone: ArUco table calibration, colour detection, scripted
pick-and-place, and a recorded episode (with its vision-judged success) for every attempt.

Perception uses only images: four ArUco markers at known spots on the table give the camera pose
(``solvePnP`` with the camera's intrinsics); objects are found as blobs that differ from the table colour
inside the workspace, classified by colour, and located by intersecting the ray through the blob centre
with the plane at the object's centre height. The instruction names the object and the direction
("move the block left"); the pick is the detected object, the place is ``PLACE_DISTANCE`` further along
the direction. The motion follows waypoints with the dataset's 7-D end-effector-delta actions through
``RobotEnv``, so every step is recorded exactly as a policy would act. Success is judged by detecting the
object again after the attempt.

On the twin, ``add_table_markers`` puts the same printed markers on its table, and the twin's own
success check is reported next to the vision verdict (never used by the pipeline).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pivla import arm
from pivla.data.episode import Episode
from pivla.data.hdf5 import write_episodes
from pivla.robot.env import RobotEnv, RobotEnvConfig

log = logging.getLogger(__name__)

ARUCO_DICT = cv2.aruco.DICT_4X4_50
MARKER_SIZE = 0.04  # m, black square edge
MARKER_BORDER = 0.006  # m, white quiet zone printed around it
# Marker centres on the table (base frame, m), ids 0..3: far enough from the arm and the objects.
MARKER_CENTRES = {0: (0.25, 0.12), 1: (0.25, -0.12), 2: (0.06, 0.17), 3: (0.06, -0.17)}
PLACE_DISTANCE = 0.09  # m along the instructed direction
DIRECTIONS = {"away": np.array([1.0, 0.0]), "left": np.array([0.0, 1.0]), "right": np.array([0.0, -1.0])}
SUCCESS_DISPLACEMENT = 0.05


@dataclass(frozen=True)
class ObjectModel:
    """What the collector knows of an object: its colour class and centre height above the table."""

    colour: str
    centre_z: float
    grasp_z: float


OBJECT_CATALOGUE = {
    "block": ObjectModel("red", 0.016, 0.018),
    "ball": ObjectModel("blue", 0.019, 0.019),
    "rock": ObjectModel("grey", 0.014, 0.016),
}


def marker_corners_3d(marker_id: int) -> np.ndarray:
    """The marker's four corners (top-left, top-right, bottom-right, bottom-left as printed) on the table.

    The printed image's "up" points away from the robot (+x) and its "right" towards -y.
    """
    cx, cy = MARKER_CENTRES[marker_id]
    h = MARKER_SIZE / 2
    return np.array([[cx + h, cy + h, 0], [cx + h, cy - h, 0], [cx - h, cy - h, 0], [cx - h, cy + h, 0]], float)


def marker_image(marker_id: int, px: int = 600) -> np.ndarray:
    """The printable marker with its white border (grey uint8); print it MARKER_SIZE wide inside."""
    inner = int(round(px * MARKER_SIZE / (MARKER_SIZE + 2 * MARKER_BORDER)))
    img = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(ARUCO_DICT), marker_id, inner)
    pad = (px - inner) // 2
    return cv2.copyMakeBorder(img, pad, px - inner - pad, pad, px - inner - pad, cv2.BORDER_CONSTANT, value=255)


def add_table_markers(robot) -> None:
    """Puts the four ArUco markers on the twin's table (a static body appended to the scene).

    Appending a body at the end keeps every existing body, geom, joint, actuator and camera id, so the
    twin's cached indices stay valid; this is checked before the model is swapped in.
    """
    # The twin (MuJoCo) is imported only to collect on it: a real arm's install has no MuJoCo.
    import mujoco

    from pivla.envs.tabletop import env as twin
    from pivla.envs.tabletop.perturb import Perturber
    from pivla.envs.tabletop.scene import asset_files, scene_xml
    from pivla.envs.tabletop.tasks import OBJECTS

    env = robot.env
    xml = scene_xml(env.task, env.perturb.n_distractors, env.perturb.n_clutter)
    geoms = []
    full = MARKER_SIZE + 2 * MARKER_BORDER
    cell = MARKER_SIZE / 6  # 4x4 data bits inside a one-cell black border
    for mid, (cx, cy) in MARKER_CENTRES.items():
        geoms.append(f'<geom type="box" size="{full / 2} {full / 2} 0.0004" pos="{cx} {cy} 0.0004" '
                     f'rgba="1 1 1 1" contype="0" conaffinity="0"/>')
        bits = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(ARUCO_DICT), mid, 6)
        h = MARKER_SIZE / 2
        for r, c in zip(*np.nonzero(bits < 128)):  # printed rows run towards -x, columns towards -y
            x, y = cx + h - (r + 0.5) * cell, cy + h - (c + 0.5) * cell
            geoms.append(f'<geom type="box" size="{cell / 2} {cell / 2} 0.0002" pos="{x} {y} 0.001" '
                         f'rgba="0 0 0 1" contype="0" conaffinity="0"/>')
    xml = xml.replace("</worldbody>", '<body name="aruco_markers">' + "".join(geoms) + "</body></worldbody>", 1)
    assets = asset_files()
    model = mujoco.MjModel.from_xml_string(xml, assets)
    old = env.model
    for kind, n in (("body", old.nbody), ("geom", old.ngeom), ("joint", old.njnt), ("actuator", old.nu),
                    ("camera", old.ncam), ("site", old.nsite)):
        for i in range(n):
            if getattr(old, kind)(i).name != getattr(model, kind)(i).name:
                raise RuntimeError(f"adding markers renumbered {kind} {i}; the twin's scene changed shape")
    model.opt.timestep = twin.PHYSICS_DT
    env.model, env.data = model, mujoco.MjData(model)
    env.perturber = Perturber(model, env.perturb, [np.array(OBJECTS[o].rgba) for o in env.task.objects])
    env._renderer = None
    robot.reset_scene(env.episode_seed)


@dataclass
class TableCalibration:
    """Camera pose w.r.t. the table (from the markers) and the intrinsics it was computed with."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    markers: int
    reprojection_px: float

    @property
    def camera_pos(self) -> np.ndarray:
        R, _ = cv2.Rodrigues(self.rvec)
        return (-R.T @ self.tvec).ravel()

    def pixel_to_plane(self, uv: np.ndarray, z: float) -> np.ndarray:
        """Intersects the ray through pixel(s) ``uv`` (N, 2) with the horizontal plane at height ``z``."""
        uv = np.atleast_2d(np.asarray(uv, float))
        R, _ = cv2.Rodrigues(self.rvec)
        rays = (R.T @ np.linalg.inv(self.K) @ np.vstack([uv.T, np.ones(len(uv))])).T
        c = self.camera_pos
        t = (z - c[2]) / rays[:, 2]
        return c + t[:, None] * rays

    def project(self, pts: np.ndarray) -> np.ndarray:
        uv, _ = cv2.projectPoints(np.asarray(pts, float), self.rvec, self.tvec, self.K, None)
        return uv.reshape(-1, 2)


def calibrate_table(image: np.ndarray, K: np.ndarray) -> TableCalibration:
    """Camera pose from the ArUco markers visible in an RGB image (at least two needed)."""
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(ARUCO_DICT), cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(gray)
    found = [] if ids is None else [(int(i), c.reshape(4, 2)) for i, c in zip(ids.ravel(), corners)
                                    if int(i) in MARKER_CENTRES]
    if len(found) < 2:
        raise RuntimeError(f"table calibration needs >= 2 of the ArUco markers {sorted(MARKER_CENTRES)}, "
                           f"saw {[i for i, _ in found]}")
    obj = np.vstack([marker_corners_3d(i) for i, _ in found])
    img = np.vstack([c for _, c in found])
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise RuntimeError("solvePnP failed on the detected markers")
    reproj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    err = float(np.sqrt(np.mean(np.sum((reproj.reshape(-1, 2) - img) ** 2, axis=1))))
    return TableCalibration(K, rvec, tvec, len(found), err)


@dataclass
class Detection:
    name: str
    colour: str
    xy: np.ndarray
    yaw: float  # grasp yaw: fingers close across the blob's short side
    area_px: int


def classify_colour(rgb: np.ndarray) -> str:
    hsv = cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0].astype(float)
    if hsv[1] < 60:
        return "grey"
    hue = hsv[0] * 2
    if hue < 25 or hue > 330:
        return "red"
    if 80 <= hue < 170:
        return "green"
    if 190 <= hue < 260:
        return "blue"
    return "other"


def detect_objects(image: np.ndarray, calib: TableCalibration, workspace: tuple[np.ndarray, np.ndarray],
                   min_area_px: int = 12) -> list[Detection]:
    """Blobs that differ from the table colour inside the table workspace, located on the table plane."""
    h, w = image.shape[:2]
    lo, hi = workspace
    corners = np.array([[lo[0], lo[1], 0], [lo[0], hi[1], 0], [hi[0], hi[1], 0], [hi[0], lo[1], 0]])
    roi = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(roi, calib.project(corners).astype(np.int32), 1)
    for mid in MARKER_CENTRES:  # ignore the printed markers
        cx, cy = MARKER_CENTRES[mid]
        s = MARKER_SIZE / 2 + MARKER_BORDER + 0.004
        quad = np.array([[cx + s, cy + s, 0], [cx + s, cy - s, 0], [cx - s, cy - s, 0], [cx - s, cy + s, 0]])
        cv2.fillConvexPoly(roi, calib.project(quad).astype(np.int32), 0)
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    table = np.median(lab[roi > 0], axis=0)
    diff = np.linalg.norm(lab - table, axis=2)
    mask = ((diff > 28) & (roi > 0)).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask)
    out = []
    for i in range(1, n):
        area = int(stats[i, cv2.CC_STAT_AREA])
        if area < min_area_px:
            continue
        pix = labels == i
        colour = classify_colour(np.median(image[pix], axis=0))
        name = next((k for k, v in OBJECT_CATALOGUE.items() if v.colour == colour), colour)
        z = OBJECT_CATALOGUE[name].centre_z if name in OBJECT_CATALOGUE else 0.015
        xy = calib.pixel_to_plane(centroids[i], z)[0, :2]
        ys, xs = np.nonzero(pix)
        plane = calib.pixel_to_plane(np.stack([xs, ys], 1), z)[:, :2].astype(np.float32)
        (_, _), (rw, rh), ang = cv2.minAreaRect(plane)
        yaw = np.deg2rad(ang) + (0.0 if rw <= rh else np.pi / 2)  # close across the short side
        out.append(Detection(name, colour, xy, float(yaw), area))
    return sorted(out, key=lambda d: -d.area_px)


def parse_instruction(instruction: str) -> tuple[str, str]:
    """("move the block left") -> ("block", "left"); raises on anything it cannot ground."""
    words = re.findall(r"[a-z]+", instruction.lower())
    objs = [w for w in words if w in OBJECT_CATALOGUE]
    dirs = [w for w in words if w in DIRECTIONS]
    if len(objs) != 1 or len(dirs) != 1:
        raise ValueError(f"cannot ground instruction {instruction!r}: objects {objs}, directions {dirs}")
    return objs[0], dirs[0]


def wrap_yaw(yaw: float, symmetry: float = np.pi / 2) -> float:
    """The equivalent grasp yaw closest to zero (keeps the wrist away from its limits)."""
    return float((yaw + symmetry / 2) % symmetry - symmetry / 2)


@dataclass
class Attempt:
    instruction: str
    obs: list[dict] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    success: bool = False
    note: str = ""


class Collector:
    """Runs scripted attempts on a ``RobotEnv`` whose robot sees the table through ``perception_camera``."""

    def __init__(self, env: RobotEnv, perception_camera, K: np.ndarray, gain: float = 1.0) -> None:
        self.env = env
        self.camera = perception_camera
        self.K = K
        self.gain = gain
        lo, hi = env.robot.safety.config.workspace_min, env.robot.safety.config.workspace_max
        self.workspace = (np.array([max(lo[0], 0.08), max(lo[1], -0.25)]),
                          np.array([min(hi[0], 0.32), min(hi[1], 0.25)]))
        self.calibration: TableCalibration | None = None

    def look(self) -> list[Detection]:
        image = self.camera.read()
        if self.calibration is None:
            self.calibration = calibrate_table(image, self.K)
            log.info("table calibration: %d markers, reprojection %.2f px, camera at %s",
                     self.calibration.markers, self.calibration.reprojection_px,
                     np.round(self.calibration.camera_pos, 3))
        return detect_objects(image, self.calibration, self.workspace)

    def _record(self, attempt: Attempt, obs: dict, action: np.ndarray) -> dict:
        attempt.obs.append(obs)
        attempt.actions.append(action.astype(np.float32))
        new_obs, *_ = self.env.step(action)
        return new_obs

    def _go(self, attempt: Attempt, obs: dict, pos: np.ndarray, yaw: float, grip: float, tol: float = 0.004,
            max_steps: int = 40) -> dict:
        """Proportional EE-delta actions towards a waypoint (top-down grasp orientation, given yaw)."""
        cfg = self.env.config
        for _ in range(max_steps):
            err = pos - obs["ee_pos"]
            cur = arm.euler_to_mat(obs["ee_ori"])
            rot = arm.mat_to_euler(arm.euler_to_mat([0.0, 0.0, yaw]) @ cur.T)
            if np.linalg.norm(err) < tol and np.max(np.abs(rot)) < 0.03:
                break
            a = np.concatenate([np.clip(self.gain * err / cfg.pos_scale, -1, 1),
                                np.clip(rot / cfg.rot_scale, -1, 1), [grip]])
            obs = self._record(attempt, obs, a)
        return obs

    def _hold(self, attempt: Attempt, obs: dict, grip: float, steps: int) -> dict:
        for _ in range(steps):
            obs = self._record(attempt, obs, np.array([0, 0, 0, 0, 0, 0, grip], float))
        return obs

    def attempt(self, instruction: str) -> tuple[Attempt, dict]:
        """One scripted pick-and-place; returns the recorded attempt and diagnostics."""
        attempt = Attempt(instruction)
        name, direction = parse_instruction(instruction)
        obs, _ = self.env.reset()
        before = [d for d in self.look() if d.name == name]
        if not before:
            attempt.note = f"no {name} detected"
            return attempt, {"detected": False}
        target = before[0]
        place = np.clip(target.xy + PLACE_DISTANCE * DIRECTIONS[direction], *self.workspace)
        yaw = wrap_yaw(target.yaw)
        model = OBJECT_CATALOGUE[name]
        hover = 0.07
        obs = self._go(attempt, obs, np.array([*target.xy, hover]), yaw, -1.0)
        obs = self._go(attempt, obs, np.array([*target.xy, model.grasp_z]), yaw, -1.0, tol=0.003)
        obs = self._hold(attempt, obs, 1.0, 5)
        obs = self._go(attempt, obs, np.array([*target.xy, hover]), yaw, 1.0)
        obs = self._go(attempt, obs, np.array([*place, hover]), yaw, 1.0)
        obs = self._go(attempt, obs, np.array([*place, model.grasp_z + 0.008]), yaw, 1.0)
        obs = self._hold(attempt, obs, -1.0, 4)
        obs = self._go(attempt, obs, np.array([*place, hover + 0.04]), yaw, -1.0)
        # Judge from the camera: the arm is up and out of the way at home.
        self.env.robot.home()
        after = [d for d in self.look() if d.name == name]
        moved = None
        if after:
            best = min(after, key=lambda d: np.linalg.norm(d.xy - place))
            delta = best.xy - target.xy
            along = float(delta @ DIRECTIONS[direction])
            across = float(np.linalg.norm(delta - along * DIRECTIONS[direction]))
            moved = (along, across)
            attempt.success = along >= SUCCESS_DISPLACEMENT and along > across
        attempt.note = f"pick {np.round(target.xy, 3).tolist()} place {np.round(place, 3).tolist()}"
        return attempt, {"detected": True, "pick_xy": target.xy, "moved": moved}


def run_on_twin(out_dir, attempts: int, suite: str = "pick_place", seed: int = 0, image_size: int = 96,
                perception_size: int = 320) -> dict:
    """Automated collection on the twin: camera-only perception, twin resets between attempts.

    Every attempt is written (success or not) to ``out_dir/<task>.hdf5``; returns the success rates of
    the vision verdict and of the twin's own check (reported, never used by the pipeline).
    """
    from pivla.envs.tabletop import list_tasks  # the twin only here (see add_table_markers)
    from pivla.robot.sim import SimCamera, SimRobot

    out_dir = Path(out_dir)
    tasks = list_tasks(suite)
    by_task: dict[str, list] = {}
    vision_ok = twin_ok = agree = 0
    rows = []
    for i in range(attempts):
        spec = tasks[i % len(tasks)]
        robot = SimRobot(suite, spec.index, seed=seed + i)
        try:
            add_table_markers(robot)
            cams = {k: SimCamera(robot, k, image_size) for k in ("agentview_rgb", "eye_in_hand_rgb")}
            perception = SimCamera(robot, "agentview_rgb", perception_size)
            env = RobotEnv(robot, cams, spec.instruction, RobotEnvConfig(realtime=False))
            collector = Collector(env, perception, perception.intrinsics())
            att, diag = collector.attempt(spec.instruction)
            truth = robot.evaluate()
        finally:
            robot.close()
        vision_ok += att.success
        twin_ok += truth
        agree += att.success == truth
        rows.append({"task": spec.name, "vision": att.success, "twin": truth, **{k: str(v) for k, v in diag.items()}})
        log.info("attempt %d %s: vision %s twin %s (%s)", i, spec.name, att.success, truth, att.note)
        if att.actions:
            obs = {k: np.stack([o[k] for o in att.obs]) for k in att.obs[0] if k != "instruction"}
            by_task.setdefault(spec.name, []).append(Episode(
                np.stack(att.actions), obs, spec.instruction, success=att.success, source="autocollect",
                meta={"twin_success": truth, "seed": seed + i}))
    for name, eps in by_task.items():
        write_episodes(out_dir / f"{name}.hdf5", eps, env_meta={"env": "tabletop", "suite": suite,
                                                               "collector": "pivla.robot.autocollect"})
    n = max(attempts, 1)
    return {"attempts": attempts, "vision_success_rate": vision_ok / n, "twin_success_rate": twin_ok / n,
            "vision_twin_agreement": agree / n, "out": str(out_dir), "per_attempt": rows}
