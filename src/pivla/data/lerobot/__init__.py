"""LeRobot dataset format v3.0, read and written with pyarrow and PyAV.

The ``lerobot`` package pins an older torch and torchvision than pivla's, so pivla implements the on-disk
format itself (as lerobot 0.4.4 writes it)::

    meta/info.json                               codebase_version "v3.0", fps, features, path templates, totals
    meta/stats.json                              per-feature min/max/mean/std/count/q01..q99
    meta/tasks.parquet                           task_index + the task string (pandas index __index_level_0__)
    meta/episodes/chunk-XXX/file-XXX.parquet     one row per episode: length, data file and row range,
                                                 per camera the mp4 file and [from_timestamp, to_timestamp)
    data/chunk-XXX/file-XXX.parquet              one row per frame, many episodes per file
    videos/<feature>/chunk-XXX/file-XXX.mp4      many episodes per file, one after the other

Mapping to pivla's :class:`~pivla.data.episode.Episode` (docs/dataset.md, "LeRobot v3.0"):
``observation.images.NAME`` <-> image key ``NAME``; ``observation.state`` <-> the proprio keys, concatenated,
with ``names`` ``["ee_pos.0", "ee_pos.1", ...]`` recording the split so reading restores the keys (other
names give one key ``state``); other low-dim keys <-> ``observation.KEY``; ``action`` <-> ``actions``;
``next.reward``/``next.done`` <-> rewards/dones; task strings <-> instructions; the episode's success,
source and meta live in extra ``pivla/*`` columns of ``meta/episodes`` (lerobot ignores them). The action
space is the ``action`` feature's ``names`` and shape (``pivla.data.action_space.infer_action_space``), or
the ``pivla/action_space`` entry pivla adds to that feature.

The modules: :mod:`pivla.data.lerobot.spec` (paths and feature names), :mod:`pivla.data.lerobot.reader`,
:mod:`pivla.data.lerobot.writer` (a whole dataset at once; :mod:`pivla.data.lerobot_append` grows one episode by
episode); :mod:`pivla.data.convert` converts between LeRobot and HDF5.
"""
