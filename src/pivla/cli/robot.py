"""``pivla robot ...``: the arm (the pivla arm, its simulated twin with ``--sim``, or an SO-101 with ``--robot so101``)
from the terminal. This module parses; what the commands do lives in ``pivla.robot`` (factory, keyboard,
teleoperation, recording, replay, calibrate, run).

Subcommands: simboard, simbus, find-port, check, calibrate, calibrate-servos, home, teleoperate, record, replay,
run, repeatability, autocollect. docs/robot.md walks through them in the order a maker uses them.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from typing import Annotated, Literal

import tyro

from pivla.control.asynchronous import ExecutionConfig, SyncConfig
from pivla.control.executors import AURDConfig, ExecutorConfig

log = logging.getLogger("pivla.robot")

Robot = Literal["pivla-arm", "so101"]


@dataclass
class ArmConfig:
    """Which arm: the pivla arm on a serial board or its simulated twin, or an SO-101 on its servo bus."""

    robot: Robot = "pivla-arm"
    """The pivla arm (or its twin with --sim), or an SO-101 (six Feetech servos, LeRobot's arm)."""
    port: str | None = None
    """Serial port of the arm's Uno, or of the SO-101's servo bus (e.g. /dev/ttyACM0)."""
    sim: bool = False
    """Use the pivla arm's simulated twin instead of a serial arm."""
    calibration: str | None = None
    """The arm's calibration file (default: arm_calibration.json for the pivla arm; for the SO-101 its
    LeRobot file <arm id>.json in LeRobot's calibration folder)."""
    arm_id: str | None = None
    """SO-101: the arm's id, which names its LeRobot calibration file."""
    suite: str = "pick_place"
    """Twin suite (with --sim)."""
    task: str = "0"
    """Twin task index or name (with --sim)."""
    seed: int = 0
    """Seed of the twin's scenes."""


@dataclass
class CameraConfig:
    """The cameras the policy reads (or a recording stores)."""

    camera: str = "0"
    """OpenCV camera index or URL of the main camera (the pivla arm's agentview_rgb, the SO-101's front);
    none for no camera."""
    wrist_camera: str | None = None
    """OpenCV camera of the wrist (eye_in_hand_rgb; the SO-101's wrist), optional."""
    image_size: int | None = None
    """Square pictures of this side in px (default: 80, the policy's, on the pivla arm; the camera's own frame
    on the SO-101)."""


def _calibration(arm: ArmConfig) -> str | None:
    if arm.calibration is None and arm.robot == "pivla-arm":
        return "arm_calibration.json"
    return arm.calibration


def _rig(arm: ArmConfig, cams: CameraConfig | None = None, instruction: str = "", **options):
    """The arm, its cameras (with ``cams``) and its env (``pivla.robot.factory.open_rig``)."""
    from pivla.robot.factory import open_rig

    camera = {}
    if cams is not None:
        camera = dict(camera=None if cams.camera.lower() == "none" else cams.camera, wrist_camera=cams.wrist_camera,
                      image_size=cams.image_size)
    return open_rig(arm.robot, port=arm.port, sim=arm.sim, calibration=_calibration(arm), arm_id=arm.arm_id,
                    suite=arm.suite, task=arm.task, seed=arm.seed, cameras=cams is not None, instruction=instruction,
                    **camera, **options)


def _pivla_arm_only(arm: ArmConfig, what: str) -> None:
    if arm.robot != "pivla-arm":
        raise ValueError(f"{what} drives the pivla arm (or its twin with --sim), not an SO-101")


def _keys(arm: ArmConfig):
    """Key presses from the terminal: polled when the env paces the loop (a real arm), every 0.1 s on the twin."""
    from pivla.robot.keyboard import terminal_keys

    return terminal_keys(0.1 if arm.sim else 0.002)


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
    robot: Robot = "pivla-arm"
    """Whose cable: the pivla arm's board or the SO-101's servo bus adapter (the search is the same)."""


def find_port(cfg: FindPortConfig) -> int:
    from pivla.robot.ports import PortNotFound, find_port

    try:
        port = find_port(input, cfg.settle_s)
    except PortNotFound as exc:
        raise SystemExit(str(exc)) from exc
    print(f"the {'SO-101' if cfg.robot == 'so101' else 'arm'}'s port is {port}; plug the cable back in")
    return 0


@dataclass
class CalibrateCommand:
    """Calibrate the arm. The pivla arm: write its servo calibration file and program its limits and home pose
    into the board (--jog: jog each joint to its zero first). The SO-101: LeRobot's guided procedure on the
    bus (the middle of the range, then every joint through its range), written to the servos and to LeRobot's
    calibration file of the arm's id."""

    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    jog: bool = False
    """The pivla arm: interactively jog each joint to its zero."""


def calibrate(cmd: CalibrateCommand) -> int:
    arm = cmd.arm
    if arm.robot == "so101":
        from pivla.robot.calibrate import calibrate_so101
        from pivla.robot.feetech import BusConfig, FeetechBus

        if not arm.port or not arm.arm_id:
            raise ValueError("calibrating an SO-101 needs its --port and the --arm-id that names its calibration")
        with FeetechBus(BusConfig(arm.port)) as bus:
            calibrate_so101(bus, arm.arm_id, _keys(arm), arm.calibration)
        return 0
    from pivla.robot.calibrate import calibrate_pivla_arm

    board = None
    if not arm.sim:
        if not arm.port:
            raise ValueError("give --port PORT for the serial arm, or --sim for the twin")
        from pivla.robot.link import Board

        board = Board.open(arm.port)
    calibrate_pivla_arm(_calibration(arm), board, cmd.jog, _keys(arm) if cmd.jog else ())
    return 0


@dataclass
class CalibrateServosCommand:
    """Create or update the arm's servo calibration file and program its limits and home pose into the board."""

    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    jog: bool = False
    """Interactively jog each joint to its zero."""


def calibrate_servos(cmd: CalibrateServosCommand) -> int:
    """The pivla arm's calibration (``pivla robot calibrate`` without --robot so101)."""
    _pivla_arm_only(cmd.arm, "calibrate-servos")
    return calibrate(CalibrateCommand(cmd.arm, cmd.jog))


def home(cmd: ArmCommand) -> int:
    from pivla.robot.factory import open_robot

    _pivla_arm_only(cmd.arm, "home")
    robot = open_robot(port=cmd.arm.port, sim=cmd.arm.sim, calibration=_calibration(cmd.arm), suite=cmd.arm.suite,
                       task=cmd.arm.task, seed=cmd.arm.seed)
    try:
        st = robot.home()
        print(f"home: q={st.q.round(3).tolist()} ee={st.ee_pos.round(3).tolist()}")
    finally:
        robot.close()
    return 0


@dataclass
class TeleoperateCommand:
    """Jog the arm from the keyboard: the pivla arm's tool (end-effector deltas), the SO-101's joints."""

    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    step_deg: float = 2.0
    """SO-101: degrees a key press moves a joint."""
    step_gripper: float = 5.0
    """SO-101: gripper percent a key press moves it."""


def teleoperate(cmd: TeleoperateCommand) -> int:
    from pivla.robot.teleoperation import help_line, jog_for
    from pivla.robot.teleoperation import teleoperate as jog_loop

    with _rig(cmd.arm, max_steps=10**9) as rig:
        jog = jog_for(rig.env, cmd.step_deg, cmd.step_gripper)
        print(help_line(jog, recording=False), flush=True)
        steps = jog_loop(rig.env, jog, _keys(cmd.arm))
    print(f"{steps} steps")
    return 0


@dataclass
class RecordCommand:
    """Teleoperate and record demonstrations into a LeRobot v3.0 dataset (right/n keeps an episode, left/r redoes
    it, esc/q stops); each kept episode is saved at once, and recording into the same folder continues it."""

    out: str
    """Dataset directory."""
    instruction: str
    """The task's instruction, stored with every episode."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)
    cameras: Annotated[CameraConfig, tyro.conf.arg(name="")] = field(default_factory=CameraConfig)
    episodes: int = 0
    """Stop after keeping this many episodes (0: when stopped)."""
    episode_time_s: float = 0.0
    """Keep an episode once it is this long (0: when a key keeps it)."""
    fps: float | None = None
    """Frames per second (default: the arm's control rate: 10 on the pivla arm, 30 on the SO-101)."""
    vcodec: Literal["libx264", "libsvtav1"] = "libx264"
    """Video codec of the cameras: H.264, or AV1 as lerobot itself writes."""
    step_deg: float = 2.0
    """SO-101: degrees a key press moves a joint."""
    step_gripper: float = 5.0
    """SO-101: gripper percent a key press moves it."""


def record(cmd: RecordCommand) -> int:
    from pivla.robot.recording import record as record_loop
    from pivla.robot.teleoperation import help_line, jog_for

    with _rig(cmd.arm, cmd.cameras, cmd.instruction, max_steps=10**9, fps=cmd.fps) as rig:
        jog = jog_for(rig.env, cmd.step_deg, cmd.step_gripper)
        print(help_line(jog, recording=True), flush=True)
        steps = round(cmd.episode_time_s * rig.env.control_hz) if cmd.episode_time_s else 0
        res = record_loop(rig.env, jog, _keys(cmd.arm), cmd.out, cmd.instruction, episodes=cmd.episodes,
                          episode_steps=steps, fps=cmd.fps, vcodec=cmd.vcodec)
    print(f"kept {res.kept} episodes ({res.frames} frames, {res.redone} redone); {res.root} holds {res.episodes}")
    return 0


@dataclass
class ReplayCommand:
    """Send a recorded episode's actions to the arm at the dataset's fps, each through the arm's safety layer."""

    dataset: str
    """LeRobot dataset directory (as `pivla robot record` writes it)."""
    episode: int = 0
    """Index of the episode."""
    arm: Annotated[ArmConfig, tyro.conf.arg(name="")] = field(default_factory=ArmConfig)


def replay(cmd: ReplayCommand) -> int:
    from pivla.robot.replay import read_episode_actions
    from pivla.robot.replay import replay as replay_loop

    episode = read_episode_actions(cmd.dataset, cmd.episode)
    with _rig(cmd.arm, max_steps=10**9, fps=episode.fps) as rig:
        sent = replay_loop(rig.env, episode)
    print(f"replayed episode {cmd.episode} of {cmd.dataset}: {len(sent)} actions at {episode.fps} fps "
          f"({episode.instruction!r})")
    return 0


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
    execution: ExecutionConfig = field(default_factory=SyncConfig)
    """--execution sync (query, then act) or async (the next query in flight while the arm executes; then
    --execution.threshold, --execution.seam; docs/latency.md)."""
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
        results = run_loop(rig.env, policy, cmd.executor, episodes=cmd.episodes, seed=cmd.arm.seed,
                           execution=cmd.execution)
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
    from pivla.robot.factory import open_robot
    from pivla.robot.repeatability import run_repeatability

    _pivla_arm_only(cmd.arm, "repeatability")
    robot = open_robot(port=cmd.arm.port, sim=cmd.arm.sim, calibration=_calibration(cmd.arm), suite=cmd.arm.suite,
                       task=cmd.arm.task, seed=cmd.arm.seed)
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
    _pivla_arm_only(cmd.arm, "autocollect")
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
