"""The ``pivla`` command line, generated from the components' typed configs by tyro.

Each command is a config dataclass (its fields and their docstrings are the flags and their help) and a
function taking it. Commands are looked up by name and imported only when used, so ``pivla robot ...``
never imports torch and ``pivla --help`` answers at once.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading

from pivla import __version__
from pivla.cli.app import DEBUG_ENV, Command, Group, run

WORKFLOW = """pivla {version}: vision-language-action policies that predict their own future, notice when they are
going wrong, and replan (PI-VLA: CMS model, unified IL + RL + state-prediction loss, AURD).

The workflow, on the simulated twin (every command has --help):
  pivla collect --suite pick_place --episodes 90 --out data/pp       expert demonstrations
  pivla train --data data/pp --out runs/pp                           the validated recipe by default
  pivla calibrate --policy runs/pp --data data/pp-valroll            AURD's thresholds, validation data only
  pivla eval --policy runs/pp --out ev/aurd --executor aurd          success with 95% CIs, traces
  pivla report --dir ev                                              tables, paired comparisons, plots
or all of it at once: pivla demo --out runs/demo
A mistake in the input prints one line naming it; --debug anywhere on the line shows the traceback.
"""

COMMANDS: dict[str, Command | Group] = {
    "demo": Command("pivla.cli.experiments", "demo",
                    "the main job on the twin: collect, train, calibrate, evaluate, report"),
    "collect": Command("pivla.cli.data", "collect", "expert demonstrations, or policy rollouts with --policy"),
    "train": Command("pivla.cli.train", "train", "train a CMS policy (the validated recipe unless told otherwise)"),
    "ensemble-runs": Command("pivla.cli.train", "ensemble_runs", "one policy from several training runs of a recipe"),
    "calibrate": Command("pivla.cli.evaluate", "calibrate", "AURD's thresholds from validation data"),
    "eval": Command("pivla.cli.evaluate", "evaluate", "evaluate a policy with an executor on a task suite"),
    "report": Command("pivla.cli.evaluate", "report", "report.md with tables, paired statistics and plots"),
    "info": Command("pivla.cli.train", "info", "a run's config, parameter counts, training status, calibration"),
    "ablate": Command("pivla.cli.experiments", "ablate", "the paper's ablation tables (4-7) on the twin"),
    "serve": Command("pivla.cli.serve", "serve", "serve a policy over a websocket (openpi's protocol)"),
    "benchmark": Group("the paper's experiments, resumable", {
        "twin": Command("pivla.cli.experiments", "benchmark_twin",
                        "Tables 2-7 and Figs. 8, 16, 17 on the twin: train, decide on validation, test, report"),
    }),
    "libero": Group("LIBERO on the official protocol", {
        "run": Command("pivla.cli.experiments", "libero_run",
                       "one suite end to end: collect, train, calibrate, evaluate on the official init states"),
        "expert": Command("pivla.cli.experiments", "libero_expert",
                          "success of the scripted experts per task, on official init states or sampled scenes"),
    }),
    "export-video": Command("pivla.cli.data", "export_video", "MP4 previews of a dataset's episodes"),
    "data": Group("datasets", {
        "convert": Command("pivla.cli.data", "convert", "convert a dataset between pivla's HDF5 and LeRobot v3"),
        "view": Command("pivla.cli.data", "view", "look at one episode: Rerun, or an MP4 and a plot"),
    }),
    "merge-lora": Command("pivla.cli.train", "merge_lora", "merge an hf run's LoRA adapters into its backbone"),
    "convert-openvla": Command("pivla.cli.train", "convert_openvla",
                               "convert OpenVLA's released checkpoint for the hf backbone (no timm)"),
    "bench": Group("speed on this machine, medians after warm-up", {
        "infer": Command("pivla.cli.bench", "infer", "batch-1 forward pass of a policy"),
        "train": Command("pivla.cli.bench", "train", "training samples/s on synthetic data"),
        "data": Command("pivla.cli.bench", "data", "memory and seconds to load a training dataset"),
        "sim": Command("pivla.cli.bench", "sim", "environment steps/s with cameras"),
        "control": Command("pivla.cli.bench", "control", "AURD's per-step overhead against fixed horizon"),
        "hf": Command("pivla.cli.bench", "hf", "CPU cost of the hf backbone stack"),
        "robot": Command("pivla.cli.bench", "robot", "serial round trips to the arm's board (or an SO-101's bus)"),
        "serve": Command("pivla.cli.bench", "serve", "round-trip latency of a served policy vs in-process"),
    }),
    "robot": Group("the real arm (or its twin with --sim)", {
        "simboard": Command("pivla.cli.robot", "simboard", "run the firmware on a simulated Uno; prints its port"),
        "simbus": Command("pivla.cli.robot", "simbus", "serve a simulated SO-101 servo bus; prints its port"),
        "find-port": Command("pivla.cli.robot", "find_port", "find the arm's serial port by unplugging its cable"),
        "check": Command("pivla.cli.robot", "check",
                         "ping the board: version, state, config, limits (--robot so101: the six joint positions)"),
        "calibrate": Command("pivla.cli.robot", "calibrate",
                             "calibrate the arm (the SO-101: LeRobot's guided procedure and calibration file)"),
        "calibrate-servos": Command("pivla.cli.robot", "calibrate_servos",
                                    "write the arm's servo calibration and program its limits into the board"),
        "home": Command("pivla.cli.robot", "home", "move to the home pose"),
        "teleoperate": Command("pivla.cli.robot", "teleoperate", "jog the arm from the keyboard"),
        "record": Command("pivla.cli.robot", "record", "teleoperate and record demonstrations into a LeRobot dataset"),
        "replay": Command("pivla.cli.robot", "replay", "send a recorded episode's actions to the arm"),
        "run": Command("pivla.cli.robot", "run_policy", "run a policy on the arm in closed loop"),
        "repeatability": Command("pivla.cli.robot", "repeatability", "move to targets repeatedly, report the scatter"),
        "autocollect": Command("pivla.cli.robot", "autocollect", "camera-only scripted collection (twin)"),
    }),
}


# Seconds a killed command has for its cleanup before its worker processes and then itself are ended outright.
SIGTERM_GRACE_S = 20.0


def _exit_on_sigterm(signum: int, frame: object) -> None:
    """``kill`` ends a command the way Ctrl-C does: through its cleanup, so worker pools are terminated with it
    (left running, a worker finishes its job for nobody) and stage clocks and partial results are saved. A cleanup
    that hangs (a signal landing inside a worker pool's bookkeeping can leave it waiting forever) is cut short after
    ``SIGTERM_GRACE_S``: what was saved was written atomically, so nothing saved is lost."""
    timer = threading.Timer(SIGTERM_GRACE_S, _end_now, args=(128 + signum,))
    timer.daemon = True
    timer.start()
    raise SystemExit(128 + signum)


def _end_now(code: int) -> None:
    for child in multiprocessing.active_children():
        child.kill()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    if argv[:1] == ["--version"]:
        print(f"pivla {__version__}")
        return 0
    if "--debug" not in argv[: argv.index("--") if "--" in argv else len(argv)]:
        return run(COMMANDS, argv, prog="pivla", intro=WORKFLOW.format(version=__version__))
    argv.remove("--debug")
    before = os.environ.get(DEBUG_ENV)
    os.environ[DEBUG_ENV] = "1"  # for this command and the worker processes it starts, not for later calls
    try:
        return run(COMMANDS, argv, prog="pivla", intro=WORKFLOW.format(version=__version__))
    finally:
        if before is None:
            os.environ.pop(DEBUG_ENV, None)
        else:
            os.environ[DEBUG_ENV] = before


if __name__ == "__main__":
    sys.exit(main())
