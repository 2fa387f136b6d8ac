"""``pivla robot ...``: the real arm (or its simulated twin with ``--sim``) from the terminal.

Subcommands: simboard, simbus, find-port, check, calibrate-servos, home, teleop, record, run, repeatability,
autocollect. docs/robot.md walks through them in the order a maker uses them; ``check`` and ``find-port``
also serve the SO-101 (``--robot so101``).
"""

from __future__ import annotations

import json
import logging
import select
import sys
import termios
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from pivla.control.executors import AURDConfig, ExecutorConfig

log = logging.getLogger("pivla.robot")

TELEOP_KEYS = {"w": (0, 1), "s": (0, -1), "a": (1, 1), "d": (1, -1), "r": (2, 1), "f": (2, -1),
               "q": (5, 1), "e": (5, -1)}
TELEOP_HELP = ("w/s: +x/-x  a/d: +y/-y  r/f: up/down  q/e: yaw  space: gripper  n: episode ok  b: episode failed  "
               "x: quit")


@dataclass
class ArmConfig:
    """Which arm: a serial one, or the simulated twin."""

    port: str | None = None
    """Serial port of the arm's Uno (e.g. /dev/ttyACM0)."""
    sim: bool = False
    """Use the simulated twin instead of a serial arm."""
    calibration: str = "arm_calibration.json"
    """Per-arm servo calibration file (JSON)."""
    suite: str = "pick_place"
    """Twin suite (with --sim)."""
    task: str = "0"
    """Twin task index or name (with --sim)."""
    seed: int = 0
    """Seed of the twin's scenes."""


@dataclass
class CameraConfig:
    """The cameras the policy reads."""

    camera: str = "0"
    """OpenCV camera index or URL for agentview_rgb."""
    wrist_camera: str | None = None
    """OpenCV camera for eye_in_hand_rgb (optional)."""
    image_size: int = 80
    """Picture side in px (the policy's)."""


def make_robot(arm: ArmConfig):
    """A SerialRobot (``--port``) or the twin (``--sim``)."""
    if arm.sim:
        from pivla.robot.sim import SimRobot

        task = int(arm.task) if str(arm.task).isdigit() else arm.task
        return SimRobot(arm.suite, task, seed=arm.seed)
    if not arm.port:
        raise SystemExit("give --port PORT for the serial arm, or --sim for the twin")
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    calib = ArmCalibration.load(arm.calibration)
    return SerialRobot(Board.open(arm.port), calib, SafetyLayer(calib))


def make_cameras(arm: ArmConfig, cams: CameraConfig, robot) -> dict:
    if arm.sim:
        from pivla.robot.sim import SimCamera

        return {k: SimCamera(robot, k, cams.image_size) for k in ("agentview_rgb", "eye_in_hand_rgb")}
    from pivla.robot.robot import OpenCVCamera

    dev = lambda s: int(s) if str(s).isdigit() else s  # noqa: E731
    out = {"agentview_rgb": OpenCVCamera(dev(cams.camera), cams.image_size)}
    if cams.wrist_camera is not None:
        out["eye_in_hand_rgb"] = OpenCVCamera(dev(cams.wrist_camera), cams.image_size)
    return out


def _rig(arm: ArmConfig, cams: CameraConfig | None = None, instruction: str = "", **options):
    """The arm, its cameras (with ``cams``) and its env (``pivla.robot.factory.open_rig``)."""
    from pivla.robot.factory import open_rig

    camera = dict(camera=cams.camera, wrist_camera=cams.wrist_camera, image_size=cams.image_size) if cams else {}
    return open_rig("pivla-arm", port=arm.port, sim=arm.sim, calibration=arm.calibration, suite=arm.suite,
                    task=arm.task, seed=arm.seed, cameras=cams is not None, instruction=instruction, **camera,
                    **options)


@dataclass
class ArmCommand:
    """An arm (serial or twin)."""

    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)


# ------------------------------------------------------------------------------------------ commands
@dataclass
class SimboardConfig:
    """The firmware on a simulated ATmega328P (simavr); prints its serial port first."""

    firmware: str | None = None
    """Firmware ELF (default: build firmware/ and use it)."""
    realtime: float = 1.0
    """Simulation speed against real time (0: unthrottled)."""
    pulses: bool = False
    """Also print the measured servo pulse widths."""


def simboard(cfg: SimboardConfig) -> int:
    from pivla.robot.simboard import SimBoard

    with SimBoard(cfg.firmware, realtime_factor=cfg.realtime) as sb:
        print(sb.port, flush=True)
        try:
            last = None
            while sb.alive():
                time.sleep(0.2)
                if cfg.pulses and sb.pulses != last:
                    last = sb.pulses
                    print("pulses_us " + " ".join(f"{w:.1f}" for w in last), flush=True)
        except KeyboardInterrupt:
            pass
    return 0


@dataclass
class SimBusCommand:
    """A simulated SO-101 bus (six STS3215 servos on a pseudo-terminal); prints its serial port first."""

    baudrate: int = 1_000_000
    """Replies are paced to this bit rate (0: as fast as the host reads)."""


def simbus(cfg: SimBusCommand) -> int:
    from pivla.robot.simbus import SimBus, SimBusConfig

    with SimBus(SimBusConfig(baudrate=cfg.baudrate)) as sim:
        print(sim.port, flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return 0


@dataclass
class CheckConfig:
    """A board's identity, state, configuration and limits; or an SO-101's six joint positions."""

    port: str
    """Serial port of the board (or of the SO-101's servo bus)."""
    bench: int = 0
    """Also time this many round trips."""
    robot: Literal["pivla-arm", "so101"] = "pivla-arm"
    """Which arm is on the port."""
    calibration: str | None = None
    """SO-101: its LeRobot calibration file, for positions in degrees (gripper 0..100)."""
    arm_id: str | None = None
    """SO-101: the arm's id; its calibration is read from LeRobot's folder unless --calibration is given."""


def check(cfg: CheckConfig) -> int:
    if cfg.robot == "so101":
        return _check_so101(cfg)
    from pivla.bench.robot import measure
    from pivla.robot.link import Board

    board = Board.open(cfg.port)
    try:
        report = {"info": board.ping().__dict__, "state": board.state().__dict__, "config": board.config().__dict__,
                  "limits": [board.limits(ch).__dict__ for ch in range(7)]}
        if cfg.bench:
            report["bench"] = measure(board, cfg.bench)
    finally:
        board.close()
    print(json.dumps(report, default=str, indent=2))
    return 0


def _check_so101(cfg: CheckConfig) -> int:
    from pivla.robot import so101
    from pivla.robot.calibration import CalibrationError
    from pivla.robot.feetech import BusConfig, BusError

    try:
        path = cfg.calibration or (so101.default_calibration_path(cfg.arm_id) if cfg.arm_id else None)
        calib = so101.SO101Calibration.load(path, cfg.arm_id) if path else None
        rows = so101.check(BusConfig(cfg.port), calib)
        bench = _bench_so101(cfg, calib) if cfg.bench else None
    except CalibrationError as exc:
        raise SystemExit(str(exc)) from exc
    except BusError as exc:
        raise SystemExit(f"no SO-101 answers on {cfg.port}: {exc}") from exc
    for r in rows:
        pos = f"{r['position']:8.2f} {r['unit']}" if "position" in r else "(no calibration: ticks only)"
        print(f"{r['motor']:<14} id {r['id']}  model {r['model']}  ticks {r['ticks']:4d}  {pos}")
    if bench:
        print(json.dumps(bench, indent=2))
    return 0


def _bench_so101(cfg: CheckConfig, calib):
    from pivla.bench.robot import measure_so101
    from pivla.robot.feetech import BusConfig
    from pivla.robot.so101 import SO101, SO101Config

    if calib is None:
        raise SystemExit("--bench on an SO-101 sends goals: give its --calibration so that they pass its limits")
    with SO101.open(BusConfig(cfg.port), calib, SO101Config(watchdog_s=0.0)) as arm:
        return measure_so101(arm, cfg.bench)


@dataclass
class FindPortConfig:
    """Find the arm's serial port: the one that goes away when its USB cable is unplugged."""

    settle_s: float = 0.5
    """Wait this long after Enter before listing the ports again."""


def find_port(cfg: FindPortConfig) -> int:
    from pivla.robot.ports import PortNotFound, find_port

    try:
        port = find_port(input, cfg.settle_s)
    except PortNotFound as exc:
        raise SystemExit(str(exc)) from exc
    print(f"the arm's port is {port}; plug the cable back in")
    return 0


@dataclass
class CalibrateServosCommand:
    """Create or update the arm's servo calibration file and program its limits and home pose into the board."""

    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    jog: bool = False
    """Interactively jog each joint to its zero."""


def calibrate_servos(cmd: CalibrateServosCommand) -> int:
    from pivla.robot.calibration import ArmCalibration

    path = Path(cmd.arm.calibration)
    calib = ArmCalibration.load(path) if path.exists() else ArmCalibration.nominal(path.stem)
    if cmd.arm.sim:
        calib.save(path)
        print(f"wrote {path} (the twin uses the nominal calibration)")
        return 0
    if not cmd.arm.port:
        raise SystemExit("give --port PORT for the serial arm, or --sim for the twin")
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    board = Board.open(cmd.arm.port)
    if cmd.jog:
        calib = jog_zero_offsets(board, calib, _keys())
    robot = SerialRobot(board, calib, SafetyLayer(calib), program_limits=True)
    for lim in calib.board_limits(robot.home_q):
        got = board.limits(lim.channel)
        if got != lim:
            raise SystemExit(f"channel {lim.channel}: board kept {got}, expected {lim}")
    calib.save(path)
    print(f"wrote {path}; board limits programmed: "
          + ", ".join(f"ch{limit.channel} {limit.min_us}-{limit.max_us} (home {limit.home_us})"
                      for limit in calib.board_limits(robot.home_q)))
    robot.close()
    return 0


def jog_zero_offsets(board, calib, keys):
    """Interactive: for each joint, jog the servo until the joint is at the model's zero, then Enter.

    Keys: '+'/'-' 10 us, ']'/'[' 50 us, 'r' reverse direction, Enter accept, 's' skip. Moves stay inside
    the board's current limits (the firmware refuses anything else).
    """
    from pivla import arm

    st = board.state()
    pulses = list(st.targets_us)
    steps = {"+": 10, "-": -10, "]": 50, "[": -50}
    for ch, name in enumerate(arm.JOINT_NAMES):
        print(f"joint {name}: jog to its zero (arm straight up), Enter to accept, s to skip", flush=True)
        for key in keys:
            if key in steps:
                lim = board.limits(ch)
                pulses[ch] = min(max(pulses[ch] + steps[key], lim.min_us), lim.max_us)
                board.set_targets(pulses, 300)
            elif key == "r":
                calib.joints[ch].direction *= -1
                print(f"  direction now {calib.joints[ch].direction:+d}", flush=True)
            elif key in ("\r", "\n"):
                calib.joints[ch].zero_us = float(pulses[ch])
                print(f"  zero_us = {pulses[ch]}", flush=True)
                break
            elif key == "s":
                break
            board.state()  # keeps the watchdog fed while the user thinks
    calib.validate()
    return calib


def _keys():
    """Single key presses from the terminal (raw mode), '' when none arrived within 0.1 s."""
    if not sys.stdin.isatty():
        raise SystemExit("this command needs an interactive terminal")
    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)
    tty.setcbreak(fd)
    try:
        while True:
            ready, _, _ = select.select([sys.stdin], [], [], 0.1)
            yield sys.stdin.read(1) if ready else ""
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


def home(cmd: ArmCommand) -> int:
    robot = make_robot(cmd.arm)
    try:
        st = robot.home()
        print(f"home: q={st.q.round(3).tolist()} ee={st.ee_pos.round(3).tolist()}")
    finally:
        robot.close()
    return 0


def teleop_actions(keys, gripper: float = -1.0):
    """Maps key presses to (action, event): 7-D EE-delta actions at half speed, events 'ok'/'fail'/'quit'."""
    for key in keys:
        a = np.zeros(7)
        event = None
        if key in TELEOP_KEYS:
            axis, sign = TELEOP_KEYS[key]
            a[axis] = 0.5 * sign
        elif key == " ":
            gripper = -gripper
        elif key == "n":
            event = "ok"
        elif key == "b":
            event = "fail"
        elif key == "x":
            event = "quit"
        a[6] = gripper
        yield a, event


@dataclass
class RecordCommand:
    """Teleoperate and record demonstrations (LIBERO layout)."""

    out: str
    """Dataset directory."""
    instruction: str
    """The task's instruction, stored with every episode."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    cameras: Annotated[CameraConfig, tyro.conf.arg(name="")] = field(default_factory=CameraConfig)


def _teleop_loop(arm: ArmConfig, record: RecordCommand | None = None) -> int:
    from pivla.robot.env import RobotEnv, RobotEnvConfig

    robot = make_robot(arm)
    cams = make_cameras(arm, record.cameras, robot) if record is not None else {}
    instruction = record.instruction if record is not None else ""
    env = RobotEnv(robot, cams, instruction, RobotEnvConfig(realtime=not arm.sim, max_steps=10**9))
    episodes = []
    print(TELEOP_HELP, flush=True)
    try:
        obs, _ = env.reset()
        steps: list[tuple[dict, np.ndarray]] = []
        for action, event in teleop_actions(_keys()):
            if event == "quit":
                break
            if event in ("ok", "fail"):
                if record is not None and steps:
                    episodes.append(_episode(steps, instruction, event == "ok"))
                    print(f"episode {len(episodes)}: {len(steps)} steps, success={event == 'ok'}", flush=True)
                steps = []
                obs, _ = env.reset()
                continue
            nxt, *_ = env.step(action)
            if record is not None:
                steps.append((obs, action))
            obs = nxt
    finally:
        robot.stop()
        env.close()
        robot.close()
    if record is not None and episodes:
        from pivla.data.format import write_episodes

        target = Path(record.out) / f"{time.strftime('%Y%m%d_%H%M%S')}.hdf5"
        path = write_episodes(target, episodes, env_meta={"env": "real_arm" if not arm.sim else "tabletop_twin"})
        print(f"wrote {len(episodes)} episodes to {path}")
    return 0


def _episode(steps, instruction: str, success: bool):
    from pivla.data.format import Episode

    keys = [k for k in steps[0][0] if k != "instruction"]
    obs = {k: np.stack([o[k] for o, _ in steps]) for k in keys}
    return Episode(np.stack([a for _, a in steps]).astype(np.float32), obs, instruction, success=success,
                   source="teleop")


def teleop(cmd: ArmCommand) -> int:
    return _teleop_loop(cmd.arm)


def record(cmd: RecordCommand) -> int:
    return _teleop_loop(cmd.arm, cmd)


@dataclass
class RunCommand:
    """A policy (local run or ws://HOST:PORT) and an executor drive the arm in closed loop; every command is
    checked against the arm's limits before it is sent."""

    policy: str
    """Run directory, or ws://HOST:PORT of a served policy."""
    instruction: str
    """What to do."""
    executor: ExecutorConfig = field(default_factory=AURDConfig)
    """How chunks become actions: --executor aurd | fixed | ensemble | adahorizon, then its options."""
    episodes: int = 1
    """Episodes to run."""
    max_steps: int = 300
    """Step limit per episode."""
    api_key: str | None = None
    """API key of a served policy."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    cameras: Annotated[CameraConfig, tyro.conf.arg(name="")] = field(default_factory=CameraConfig)


def run_policy(cmd: RunCommand) -> int:
    from pivla.robot.run import run_policy as run_loop
    from pivla.serving.client import open_policy

    policy = open_policy(cmd.policy, api_key=cmd.api_key)
    with _rig(cmd.arm, cmd.cameras, cmd.instruction, max_steps=cmd.max_steps) as rig:
        results = run_loop(rig.env, policy, cmd.executor, episodes=cmd.episodes, seed=cmd.arm.seed)
    print(json.dumps(results, default=str, indent=2))
    return 0


@dataclass
class RepeatabilityCommand:
    """Move to targets repeatedly and report the scatter of the reached positions (mm)."""

    targets: int = 5
    """Targets in the workspace."""
    repeats: int = 10
    """Visits of each target."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)


def repeatability(cmd: RepeatabilityCommand) -> int:
    from pivla.robot.repeatability import run_repeatability

    robot = make_robot(cmd.arm)
    try:
        report = run_repeatability(robot, cmd.repeats, cmd.targets, seed=cmd.arm.seed)
    finally:
        robot.close()
    print(json.dumps(report, indent=2))
    return 0


@dataclass
class AutocollectCommand:
    """Camera-only scripted pick-and-place collection on the twin."""

    out: str
    """Dataset directory."""
    attempts: int = 50
    """Pick-and-place attempts."""
    image_size: int = 80
    """Picture side in px."""
    verbose: bool = False
    """Also print every attempt."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)


def autocollect(cmd: AutocollectCommand) -> int:
    if not cmd.arm.sim:
        raise SystemExit("autocollect runs on the twin (--sim); on the real arm use the Collector class with "
                         "a SerialRobot, an OpenCVCamera and printed markers (docs/robot.md)")
    from pivla.robot.autocollect import run_on_twin

    report = run_on_twin(cmd.out, cmd.attempts, cmd.arm.suite, cmd.arm.seed, cmd.image_size)
    rows = report.pop("per_attempt")
    if cmd.verbose:
        report["per_attempt"] = rows
    print(json.dumps(report, indent=2))
    return 0
