"""``pivla robot ...``: the real arm (or its simulated twin with ``--sim``) from the terminal.

Subcommands: simboard, check, calibrate, home, teleop, record, run, repeatability, autocollect.
docs/robot.md walks through them in the order a maker uses them.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

log = logging.getLogger("pivla.robot")

TELEOP_KEYS = {"w": (0, 1), "s": (0, -1), "a": (1, 1), "d": (1, -1), "r": (2, 1), "f": (2, -1),
               "q": (5, 1), "e": (5, -1)}
TELEOP_HELP = "w/s: +x/-x  a/d: +y/-y  r/f: up/down  q/e: yaw  space: gripper  n: episode ok  b: episode failed  x: quit"


def _robot_args(p: argparse.ArgumentParser, cameras: bool = False) -> None:
    p.add_argument("--port", help="serial port of the arm's Uno (e.g. /dev/ttyACM0)")
    p.add_argument("--sim", action="store_true", help="use the simulated twin instead of a serial arm")
    p.add_argument("--calibration", default="arm_calibration.json", help="per-arm calibration file (JSON)")
    p.add_argument("--suite", default="pick_place", help="twin suite (with --sim)")
    p.add_argument("--task", default="0", help="twin task index or name (with --sim)")
    p.add_argument("--seed", type=int, default=0)
    if cameras:
        p.add_argument("--camera", default="0", help="OpenCV camera index or URL for agentview_rgb")
        p.add_argument("--wrist-camera", default=None, help="OpenCV camera for eye_in_hand_rgb (optional)")
        p.add_argument("--image-size", type=int, default=96)


def make_robot(args):
    """A SerialRobot (``--port``) or the twin (``--sim``)."""
    if args.sim:
        from pivla.robot.sim import SimRobot

        task = int(args.task) if str(args.task).isdigit() else args.task
        return SimRobot(args.suite, task, seed=args.seed)
    if not args.port:
        raise SystemExit("give --port PORT for the serial arm, or --sim for the twin")
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    calib = ArmCalibration.load(args.calibration)
    return SerialRobot(Board.open(args.port), calib, SafetyLayer(calib))


def make_cameras(args, robot) -> dict:
    if args.sim:
        from pivla.robot.sim import SimCamera

        return {k: SimCamera(robot, k, args.image_size) for k in ("agentview_rgb", "eye_in_hand_rgb")}
    from pivla.robot.robot import OpenCVCamera

    dev = lambda s: int(s) if str(s).isdigit() else s  # noqa: E731
    cams = {"agentview_rgb": OpenCVCamera(dev(args.camera), args.image_size)}
    if args.wrist_camera is not None:
        cams["eye_in_hand_rgb"] = OpenCVCamera(dev(args.wrist_camera), args.image_size)
    return cams


# ------------------------------------------------------------------------------------------ commands
def cmd_simboard(args) -> int:
    from pivla.robot.simboard import SimBoard

    with SimBoard(args.firmware, realtime_factor=args.realtime) as sb:
        print(sb.port, flush=True)
        try:
            last = None
            while sb.alive():
                time.sleep(0.2)
                if args.pulses and sb.pulses != last:
                    last = sb.pulses
                    print("pulses_us " + " ".join(f"{w:.1f}" for w in last), flush=True)
        except KeyboardInterrupt:
            pass
    return 0


def cmd_check(args) -> int:
    from pivla.robot.bench import measure
    from pivla.robot.link import Board

    board = Board.open(args.port)
    try:
        report = {"info": board.ping().__dict__, "state": board.state().__dict__, "config": board.config().__dict__,
                  "limits": [board.limits(ch).__dict__ for ch in range(7)]}
        if args.bench:
            report["bench"] = measure(board, args.bench)
    finally:
        board.close()
    print(json.dumps(report, default=str, indent=2))
    return 0


def cmd_calibrate(args) -> int:
    """Creates or updates the calibration file and programs its limits and home pose into the board."""
    from pathlib import Path

    from pivla.robot.calibration import ArmCalibration

    path = Path(args.calibration)
    calib = ArmCalibration.load(path) if path.exists() else ArmCalibration.nominal(path.stem)
    if args.sim:
        calib.save(path)
        print(f"wrote {path} (the twin uses the nominal calibration)")
        return 0
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    board = Board.open(args.port)
    if args.jog:
        calib = jog_zero_offsets(board, calib, _keys())
    robot = SerialRobot(board, calib, SafetyLayer(calib), program_limits=True)
    for lim in calib.board_limits(robot.home_q):
        got = board.limits(lim.channel)
        if got != lim:
            raise SystemExit(f"channel {lim.channel}: board kept {got}, expected {lim}")
    calib.save(path)
    print(f"wrote {path}; board limits programmed: "
          + ", ".join(f"ch{l.channel} {l.min_us}-{l.max_us} (home {l.home_us})" for l in calib.board_limits(robot.home_q)))
    robot.close()
    return 0


def jog_zero_offsets(board, calib, keys):
    """Interactive: for each joint, jog the servo until the joint is at the model's zero, then Enter.

    Keys: '+'/'-' 10 us, ']'/'[' 50 us, 'r' reverse direction, Enter accept, 's' skip. Moves stay inside
    the board's current limits (the firmware refuses anything else).
    """
    from pivla.envs.tabletop import arm

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
    import select
    import termios
    import tty

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


def cmd_home(args) -> int:
    robot = make_robot(args)
    try:
        st = robot.home()
        print(f"home: q={st.q.round(3).tolist()} ee={st.ee_pos.round(3).tolist()}")
    finally:
        robot.close()
    return 0


def teleop_actions(keys, gripper: float = -1.0):
    """Maps key presses to (action, event): 7-D EE-delta actions at half speed, events 'ok'/'fail'/'quit'."""
    import numpy as np

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


def _teleop_loop(args, record_to=None) -> int:
    import numpy as np

    from pivla.robot.env import RobotEnv, RobotEnvConfig

    robot = make_robot(args)
    cams = make_cameras(args, robot) if record_to is not None else {}
    instruction = getattr(args, "instruction", "") or ""
    env = RobotEnv(robot, cams, instruction, RobotEnvConfig(realtime=not args.sim, max_steps=10**9))
    episodes = []
    print(TELEOP_HELP, flush=True)
    try:
        obs, _ = env.reset()
        steps: list[tuple[dict, np.ndarray]] = []
        for action, event in teleop_actions(_keys()):
            if event == "quit":
                break
            if event in ("ok", "fail"):
                if record_to is not None and steps:
                    episodes.append(_episode(steps, instruction, event == "ok"))
                    print(f"episode {len(episodes)}: {len(steps)} steps, success={event == 'ok'}", flush=True)
                steps = []
                obs, _ = env.reset()
                continue
            nxt, *_ = env.step(action)
            if record_to is not None:
                steps.append((obs, action))
            obs = nxt
    finally:
        robot.stop()
        env.close()
        robot.close()
    if record_to is not None and episodes:
        from pivla.data.format import write_episodes

        path = write_episodes(record_to, episodes, env_meta={"env": "real_arm" if not args.sim else "tabletop_twin"})
        print(f"wrote {len(episodes)} episodes to {path}")
    return 0


def _episode(steps, instruction: str, success: bool):
    import numpy as np

    from pivla.data.format import Episode

    keys = [k for k in steps[0][0] if k != "instruction"]
    obs = {k: np.stack([o[k] for o, _ in steps]) for k in keys}
    return Episode(np.stack([a for _, a in steps]).astype(np.float32), obs, instruction, success=success,
                   source="teleop")


def cmd_teleop(args) -> int:
    return _teleop_loop(args)


def cmd_record(args) -> int:
    from pathlib import Path

    out = Path(args.out)
    return _teleop_loop(args, record_to=out / f"{time.strftime('%Y%m%d_%H%M%S')}.hdf5")


def cmd_run(args) -> int:
    """The closed loop on the arm: a policy run and an executor from pivla.control."""
    try:
        from pivla import load_policy
        from pivla.control import make_executor, run_episode
    except ImportError as exc:
        raise SystemExit(f"pivla robot run needs pivla.control (make_executor, run_episode) and load_policy: {exc}")
    from pivla.robot.env import RobotEnv, RobotEnvConfig

    robot = make_robot(args)
    env = RobotEnv(robot, make_cameras(args, robot), args.instruction,
                   RobotEnvConfig(realtime=not args.sim, max_steps=args.max_steps))
    policy = load_policy(args.policy)
    results = []
    try:
        for ep in range(args.episodes):
            results.append(run_episode(env, policy, make_executor(args.executor), seed=args.seed + ep).summary())
            log.info("episode %d: %s", ep, results[-1])
    finally:
        robot.stop()
        env.close()
        robot.close()
    print(json.dumps(results, default=str, indent=2))
    return 0


def cmd_repeatability(args) -> int:
    from pivla.robot.repeatability import run_repeatability

    robot = make_robot(args)
    try:
        report = run_repeatability(robot, args.repeats, args.targets, seed=args.seed)
    finally:
        robot.close()
    print(json.dumps(report, indent=2))
    return 0


def cmd_autocollect(args) -> int:
    if not args.sim:
        raise SystemExit("autocollect runs on the twin (--sim); on the real arm use the Collector class with "
                         "a SerialRobot, an OpenCVCamera and printed markers (docs/robot.md)")
    from pivla.robot.autocollect import run_on_twin

    report = run_on_twin(args.out, args.attempts, args.suite, args.seed, args.image_size)
    rows = report.pop("per_attempt")
    if args.verbose:
        report["per_attempt"] = rows
    print(json.dumps(report, indent=2))
    return 0


def register(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="robot_command", metavar="SUBCOMMAND", required=True)

    p = sub.add_parser("simboard", help="run the firmware on a simulated Uno; prints the serial port first")
    p.add_argument("--firmware", default=None, help="firmware ELF (default: build firmware/ and use it)")
    p.add_argument("--realtime", type=float, default=1.0, help="simulation speed vs real time (0: unthrottled)")
    p.add_argument("--pulses", action="store_true", help="also print measured servo pulse widths")
    p.set_defaults(func=cmd_simboard)

    p = sub.add_parser("check", help="ping the board, print version, state, config and limits")
    p.add_argument("--port", required=True)
    p.add_argument("--bench", type=int, default=0, metavar="N", help="also time N round trips")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("calibrate", help="write the calibration file and program limits into the board")
    _robot_args(p)
    p.add_argument("--jog", action="store_true", help="interactively jog each joint to its zero")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("home", help="move to the home pose")
    _robot_args(p)
    p.set_defaults(func=cmd_home)

    p = sub.add_parser("teleop", help="keyboard teleoperation in the terminal")
    _robot_args(p)
    p.set_defaults(func=cmd_teleop)

    p = sub.add_parser("record", help="teleoperate and record demonstrations (LIBERO layout)")
    _robot_args(p, cameras=True)
    p.add_argument("--out", required=True, help="dataset directory")
    p.add_argument("--instruction", required=True)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("run", help="run a trained policy on the arm in closed loop")
    _robot_args(p, cameras=True)
    p.add_argument("--policy", required=True, help="training run directory")
    p.add_argument("--executor", default="aurd")
    p.add_argument("--instruction", required=True)
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--max-steps", type=int, default=300)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("repeatability", help="move to targets repeatedly and report the scatter (mm)")
    _robot_args(p)
    p.add_argument("--targets", type=int, default=5)
    p.add_argument("--repeats", type=int, default=10)
    p.set_defaults(func=cmd_repeatability)

    p = sub.add_parser("autocollect", help="camera-only scripted pick-and-place collection (twin)")
    _robot_args(p)
    p.add_argument("--out", required=True, help="dataset directory")
    p.add_argument("--attempts", type=int, default=50)
    p.add_argument("--image-size", type=int, default=96)
    p.set_defaults(func=cmd_autocollect)

    def configure_logging(args):
        logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s")
        return args._func(args)

    for sp in sub.choices.values():
        sp.set_defaults(_func=sp.get_default("func"), func=configure_logging)
