"""What LoRA adapts in a vision-language model, and activation checkpointing across transformers versions."""

from __future__ import annotations

from torch import nn


def lora_target_names(model: nn.Module, targets: tuple[str, ...]) -> list[str]:
    """Full names of the language model's Linear layers whose last name component is in ``targets``
    (``all-linear``: every Linear of the language model except the output head)."""
    names = []
    for name, mod in model.named_modules():
        if not isinstance(mod, nn.Linear) or "language_model." not in name or name.endswith("lm_head"):
            continue
        if "all-linear" in targets or name.rsplit(".", 1)[-1] in targets:
            names.append(name)
    if not names:
        raise ValueError(f"no Linear layer named {list(targets)} in the language model")
    return names


def enable_activation_checkpointing(model: nn.Module, kwargs: dict | None) -> None:
    """``activation_checkpointing_enable`` (transformers >= 5.20) or its older name."""
    if hasattr(model, "activation_checkpointing_enable"):
        model.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)
