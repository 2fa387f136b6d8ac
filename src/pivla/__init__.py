"""pivla: PI-VLA policies that predict their own future, notice when they go wrong, and replan."""

__version__ = "0.1.0"


def load_policy(run_dir, device: str = "auto", threads: int = 0, gripper_head: str | None = None,
                encoder_runtime: str = "auto"):
    """``policy = load_policy(run_dir)``; ``policy.infer(obs)``. See ``pivla.policy``."""
    from pivla.policy import load_policy as _load

    return _load(run_dir, device=device, threads=threads, gripper_head=gripper_head, encoder_runtime=encoder_runtime)


__all__ = ["load_policy", "__version__"]
