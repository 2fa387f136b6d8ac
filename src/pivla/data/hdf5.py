"""pivla's HDF5 dataset: episode files in the layout of LIBERO's official demonstration HDF5 files.

A dataset is a directory of ``.hdf5`` files. Each file holds::

    data/                         attrs: problem_info (JSON with "language_instruction"), [pivla_version],
                                         [action_space] (JSON, ``ActionSpace.to_dict``)
    data/demo_<i>/                attrs: num_samples, [language_instruction], [success], [source]
        actions        (T, D) float   as the action space says (absent: EE_DELTA, xyz, Euler rpy, gripper)
        rewards        (T,)   float
        dones          (T,)   uint8/bool
        obs/agentview_rgb    (T, H, W, 3) uint8
        obs/eye_in_hand_rgb  (T, H, W, 3) uint8   (optional)
        obs/ee_pos (T, 3), obs/ee_ori (T, 3), obs/gripper_states (T, 2), obs/joint_states (T, J)

The per-demo attributes in brackets are pivla's extensions; files without them (LIBERO's own) load with
the file-level instruction and ``success=True``. See docs/dataset.md.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

import h5py
import numpy as np

from pivla.data.action_space import EE_DELTA, ActionSpace
from pivla.data.episode import (
    IMAGE_KEYS,
    PROPRIO_KEYS,
    STATE_KEY,
    DatasetError,
    DatasetLayout,
    Episode,
    check_destination,
)
from pivla.io import atomic_dir, atomic_path

REQUIRED_DEMO_KEYS = ("actions", "rewards", "dones", "obs")  # cameras: whichever a reader asks for
ACTION_SPACE_ATTR = "action_space"


def write_episodes(path: str | Path, episodes: list[Episode], env_meta: dict | None = None,
                   action_space: ActionSpace = EE_DELTA) -> Path:
    """Write episodes to one HDF5 file atomically (temp file + rename), so a crash never leaves half a file.
    ``action_space``: what the episodes' action rows mean (the twin's and LIBERO's by default)."""
    path = Path(path)
    if not episodes:
        raise DatasetError(f"{path}: refusing to write a file with no episodes")
    for ep in episodes:
        if ep.actions.shape[1] != action_space.dim:
            raise DatasetError(f"{path}: episode {ep.instruction!r} has {ep.actions.shape[1]}-D actions, the "
                               f"action space is {action_space.describe()}")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"language_instruction": episodes[0].instruction})
        data.attrs["env_args"] = json.dumps(env_meta or {})
        data.attrs["pivla_version"] = 1
        data.attrs[ACTION_SPACE_ATTR] = json.dumps(action_space.to_dict())
        total = 0
        for i, ep in enumerate(episodes):
            g = data.create_group(f"demo_{i}")
            g.attrs["num_samples"] = len(ep)
            g.attrs["language_instruction"] = ep.instruction
            g.attrs["success"] = bool(ep.success)
            g.attrs["source"] = ep.source
            if ep.meta:
                g.attrs["meta"] = json.dumps(ep.meta)
            g.create_dataset("actions", data=ep.actions)
            g.create_dataset("rewards", data=ep.rewards)
            g.create_dataset("dones", data=ep.dones)
            obs = g.create_group("obs")
            for key, arr in ep.obs.items():
                arr = np.asarray(arr)
                if key in IMAGE_KEYS:
                    obs.create_dataset(key, data=arr, chunks=(1, *arr.shape[1:]), compression="lzf")
                else:
                    obs.create_dataset(key, data=arr)
            total += len(ep)
        data.attrs["total"] = total
    return path


def _demo_sort_key(name: str) -> tuple[int, str]:
    suffix = name.rsplit("_", 1)[-1]
    return (int(suffix), name) if suffix.isdigit() else (1 << 30, name)


def read_episodes(path: str | Path, obs_keys: tuple[str, ...] | None = None) -> list[Episode]:
    """Read every ``demo_*`` of one file. ``obs_keys`` limits (and requires) the observation keys loaded."""
    return list(iter_episodes(path, obs_keys))


# what h5py raises on a damaged file, by where the damage lies (structure, heap, data)
_H5_DAMAGE = (OSError, KeyError, ValueError, RuntimeError)


def iter_episodes(path: str | Path, obs_keys: tuple[str, ...] | None = None) -> Iterator[Episode]:
    """``read_episodes`` one episode at a time, so that a reader keeps no more than one in memory."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"{path}: not a readable HDF5 file ({e})") from e
    with f:
        try:
            yield from _demos(path, f, obs_keys)
        except DatasetError:
            raise
        except _H5_DAMAGE as e:
            raise DatasetError(f"{path}: truncated or corrupt ({e})") from e


def _demos(path: Path, f: h5py.File, obs_keys: tuple[str, ...] | None) -> Iterator[Episode]:
    """The episodes of an open file, checked key by key."""
    if "data" not in f:
        raise DatasetError(f"{path}: missing key 'data'")
    data = f["data"]
    try:
        problem = json.loads(data.attrs.get("problem_info", "{}"))
    except (TypeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: attribute data.problem_info is not valid JSON") from e
    file_instruction = problem.get("language_instruction", "")
    if isinstance(file_instruction, list):  # some LIBERO files store it as a list of words
        file_instruction = " ".join(file_instruction)
    space = _action_space(path, data)
    demos = sorted((k for k in data if k.startswith("demo")), key=_demo_sort_key)
    if not demos:
        raise DatasetError(f"{path}: group 'data' holds no demo_<i> groups")
    for name in demos:
        g = data[name]
        for key in REQUIRED_DEMO_KEYS:
            if key not in g:
                raise DatasetError(f"{path}: missing key 'data/{name}/{key}'")
        keys = obs_keys if obs_keys is not None else tuple(g["obs"].keys())
        obs = {}
        try:
            for key in keys:
                if key not in g["obs"]:
                    raise DatasetError(f"{path}: missing key 'data/{name}/obs/{key}'")
                obs[key] = g["obs"][key][()]
            instruction = g.attrs.get("language_instruction", file_instruction)
            if isinstance(instruction, bytes):
                instruction = instruction.decode()
            ep = Episode(
                actions=g["actions"][()],
                rewards=g["rewards"][()],
                dones=g["dones"][()],
                obs=obs,
                instruction=str(instruction),
                success=bool(g.attrs.get("success", True)),
                source=str(g.attrs.get("source", "expert")),
                meta=json.loads(g.attrs["meta"]) if "meta" in g.attrs else {},
            )
        except DatasetError as e:
            if str(e).startswith(str(path)):
                raise e
            raise DatasetError(f"{path}: data/{name}: {e}") from e
        except _H5_DAMAGE as e:
            raise DatasetError(f"{path}: data/{name} is truncated or corrupt ({e})") from e
        if ep.actions.shape[1] != space.dim:
            raise DatasetError(f"{path}: data/{name}/actions has {ep.actions.shape[1]} dims, the file's action space "
                               f"is {space.describe()}")
        img = obs.get("agentview_rgb")
        if img is not None and (img.ndim != 4 or img.shape[-1] != 3 or img.dtype != np.uint8):
            raise DatasetError(
                f"{path}: data/{name}/obs/agentview_rgb must be (T,H,W,3) uint8, got {img.shape} {img.dtype}"
            )
        yield ep


def _action_space(path: Path, data: h5py.Group) -> ActionSpace:
    """The ``data.action_space`` attribute; files without one (LIBERO's, pivla's older ones) hold EE_DELTA."""
    if ACTION_SPACE_ATTR not in data.attrs:
        return EE_DELTA
    try:
        return ActionSpace.from_dict(json.loads(data.attrs[ACTION_SPACE_ATTR]))
    except (TypeError, ValueError) as e:  # JSONDecodeError is a ValueError
        raise DatasetError(f"{path}: attribute data.{ACTION_SPACE_ATTR} is not an action space ({e})") from None


def read_action_space(path: str | Path) -> ActionSpace:
    """What the actions of one file mean (EE_DELTA for a file that does not say)."""
    try:
        with h5py.File(path, "r") as f:
            if "data" not in f:
                raise DatasetError(f"{path}: missing key 'data'")
            return _action_space(Path(path), f["data"])
    except OSError as e:
        raise DatasetError(f"{path}: not a readable HDF5 file ({e})") from e


def hdf5_action_space(files: list[Path]) -> ActionSpace:
    """The action space of a set of files, which must all declare the same one."""
    spaces = {path: read_action_space(path) for path in files}
    first = files[0]
    for path, space in spaces.items():
        if space != spaces[first]:
            raise DatasetError(f"{path} has actions {space.describe()}, {first} has {spaces[first].describe()}: "
                               "one dataset holds one action space")
    return spaces[first]


def hdf5_layout(root: str | Path) -> DatasetLayout:
    """The layout of a directory of HDF5 files, from the first episode's keys and shapes (no pictures read):
    LIBERO's cameras then any other (T, H, W, 3) uint8 key; pivla's proprio keys when all are there, else a
    converted ``state``, else none."""
    files = dataset_files(root)
    space = hdf5_action_space(files)
    try:
        with h5py.File(files[0], "r") as f:
            demos = sorted((k for k in f["data"] if k.startswith("demo")), key=_demo_sort_key)
            if not demos:
                raise DatasetError(f"{files[0]}: group 'data' holds no demo_<i> groups")
            obs = f["data"][demos[0]]["obs"]
            shapes = {k: (obs[k].shape, obs[k].dtype) for k in obs}
    except _H5_DAMAGE as e:
        raise DatasetError(f"{files[0]}: no readable data/demo_<i>/obs group ({e})") from e
    images = [k for k, (shape, dtype) in shapes.items() if len(shape) == 4 and shape[-1] == 3 and dtype == np.uint8]
    vectors = {k: int(shape[-1]) if len(shape) == 2 else 1 for k, (shape, _) in shapes.items() if len(shape) in (1, 2)}
    if all(k in vectors for k in PROPRIO_KEYS):
        proprio: tuple[str, ...] = PROPRIO_KEYS
    else:
        proprio = (STATE_KEY,) if STATE_KEY in vectors else ()
    cameras = (*(k for k in IMAGE_KEYS if k in images), *(k for k in images if k not in IMAGE_KEYS))
    return DatasetLayout(cameras=cameras, proprio=proprio, vectors=vectors, action_space=space)


def read_env_meta(path: str | Path) -> dict:
    """A file's ``data.env_args`` (how it was recorded: env, control rate, seeds...), ``{}`` when absent."""
    try:
        with h5py.File(path, "r") as f:
            return json.loads(f["data"].attrs.get("env_args", "{}")) if "data" in f else {}
    except (OSError, json.JSONDecodeError, TypeError) as e:
        raise DatasetError(f"{path}: unreadable HDF5 file or env_args ({e})") from e


def dataset_files(root: str | Path) -> list[Path]:
    """The ``.hdf5`` files of a dataset directory (or the file itself), sorted for reproducibility. Hidden
    files and folders (e.g. an evaluation's per-episode recordings, merged beside them) are not part of it."""
    root = Path(root)
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory does not exist")
    files = sorted(p for p in root.rglob("*.hdf5")
                   if not any(part.startswith(".") for part in p.relative_to(root).parts))
    if not files:
        raise DatasetError(f"{root}: no .hdf5 files found")
    return files


def hdf5_fps(files: list[Path]) -> int | None:
    """The control rate recorded in the files' ``env_args`` (pivla's ``control_hz``, LIBERO's
    ``env_kwargs.control_freq``), if any."""
    rates = set()
    for path in files:
        env = read_env_meta(path)
        rate = env.get("control_hz") or (env.get("env_kwargs") or {}).get("control_freq")
        if rate:
            rates.add(round(float(rate)))
    if len(rates) > 1:
        raise DatasetError(f"the files record different control rates {sorted(rates)} Hz: give fps")
    return rates.pop() if rates else None


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")[:80] or "task"


def write_hdf5(root: str | Path, episodes: Iterable[Episode], env_meta: dict, episodes_per_file: int = 50,
               overwrite: bool = False, action_space: ActionSpace = EE_DELTA) -> Path:
    """Write episodes as LIBERO-layout files, one per run of consecutive episodes of one task (at most
    ``episodes_per_file``), named ``<n>_<task>_demo.hdf5`` so their sorted order is the episode order."""
    root = Path(root)
    check_destination(root, overwrite)
    if episodes_per_file < 1:
        raise DatasetError(f"episodes_per_file must be at least 1, got {episodes_per_file}")
    with atomic_dir(root) as tmp:
        run: list[Episode] = []
        n = 0
        for ep in episodes:
            if run and (ep.instruction != run[0].instruction or len(run) >= episodes_per_file):
                write_episodes(tmp / f"{n:05d}_{_slug(run[0].instruction)}_demo.hdf5", run, env_meta, action_space)
                run, n = [], n + 1
            run.append(ep)
        if not run:
            raise DatasetError("refusing to write a dataset with no episodes")
        write_episodes(tmp / f"{n:05d}_{_slug(run[0].instruction)}_demo.hdf5", run, env_meta, action_space)
    return root
