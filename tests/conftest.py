import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory):
    """A tiny LIBERO-layout dataset (4 goals x 4 episodes x 20 steps, 32 px) shared by core tests."""
    from pivla.data.synthetic import make_synthetic_dataset

    return make_synthetic_dataset(tmp_path_factory.mktemp("syn") / "data", episodes_per_goal=4, T=20, size=32, failures=1)


def tiny_train_config(data, out, **overrides):
    from pivla.model.config import BackboneConfig, ModelConfig
    from pivla.training.trainer import TrainConfig

    model = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=2, vision_channels=(16, 32, 32, 32)))
    kw = dict(data=str(data), out=str(out), steps=20, batch_size=8, warmup=5, log_every=5, eval_every=10,
              ckpt_every=10, value_refresh_every=10, progress=False, model=model, threads=2)
    kw.update(overrides)
    return TrainConfig(**kw)
