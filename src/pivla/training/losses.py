"""The unified objective of PI-VLA (paper Eqs. 8-11), one function per term.

All terms take the model's ``CMSOutput`` fields and a batch of tensors from ``ChunkDataset``; masks make
padded chunk steps (past the episode end) and non-imitation episodes (failed rollouts) count for nothing.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from pivla.model.cms import CMSModel, CMSOutput
from pivla.training.config import LossConfig

SIGMA_MIN, SIGMA_MAX, ADV_CLIP, RESIDUAL_CAP = 0.05, 1.0, 3.0, 3.0


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


def imitation_loss(logits: torch.Tensor, continuous: torch.Tensor, bins: torch.Tensor, actions: torch.Tensor,
                   mask: torch.Tensor, lam: float = 1.0, use_discrete: bool = True,
                   use_continuous: bool = True) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 9: L_IL = CE(expert bins, discrete logits) + lam * SmoothL1(expert chunk, A_c).

    logits (B,K,D,n_bins), continuous (B,K,D), bins (B,K,D) int, actions (B,K,D) normalized,
    mask (B,K): 1 for real chunk steps of imitation episodes.
    """
    m = mask.unsqueeze(-1).expand_as(actions)
    ce = F.cross_entropy(logits.flatten(0, 2).float(), bins.flatten(), reduction="none").view_as(actions)
    l1 = F.smooth_l1_loss(continuous.float(), actions, reduction="none", beta=0.05)
    ce_m, l1_m = _masked_mean(ce, m), _masked_mean(l1, m)
    total = (ce_m if use_discrete else 0.0) + (lam * l1_m if use_continuous else 0.0)
    return total, {"il_ce": ce_m.detach(), "il_l1": l1_m.detach()}


def actor_loss(continuous: torch.Tensor, log_sigma: torch.Tensor, actions_taken: torch.Tensor,
               advantages: torch.Tensor, mask: torch.Tensor, positive_only: bool = False) -> torch.Tensor:
    """Eq. 10: -(1/K) sum_k log N(a_{t,k} | A_c[k], sigma^2) * A_hat_{t,k}.

    a_{t,k} are the actions actually taken in the data; a deterministic head would give log pi of its own
    output no gradient (docs/method.md, "Unified loss"). Advantages come normalised and detached from GAE.

    With negative advantages this objective is unbounded below: the mean runs away from bad actions
    quadratically, and sigma can collapse. So sigma stays in [SIGMA_MIN, SIGMA_MAX], advantages are clipped
    to +-ADV_CLIP standard deviations, and the squared standardised residual is capped at RESIDUAL_CAP^2
    (no gradient pushes the mean further than RESIDUAL_CAP sigmas from an action), in the spirit of PPO's
    clipping.

    ``positive_only`` zeroes the negative advantages: the term then only pulls towards actions that did better
    than expected. With DART data the advantages describe the executed, noisy trajectory while the action
    they weight is the expert's clean label, so a negative advantage pushes the head away from the label.
    """
    log_sigma = log_sigma.clamp(math.log(SIGMA_MIN), math.log(SIGMA_MAX))
    advantages = advantages.detach().clamp(0.0 if positive_only else -ADV_CLIP, ADV_CLIP)
    z2 = (((actions_taken - continuous.float()) / log_sigma.exp()) ** 2).clamp(max=RESIDUAL_CAP**2)
    logp = (-0.5 * z2 - log_sigma - 0.5 * math.log(2 * math.pi)).sum(-1)
    return -_masked_mean(logp * advantages, mask)


def critic_loss(values: torch.Tensor, value_now: torch.Tensor, returns: torch.Tensor,
                mask: torch.Tensor) -> torch.Tensor:
    """Regress [V(s_t), V[1..H]] onto the lambda-returns of the states they describe (masked past the end)."""
    pred = torch.cat([value_now.unsqueeze(1), values], dim=1).float()
    return _masked_mean((pred - returns) ** 2, mask)


def state_prediction_loss(pred_latents: torch.Tensor, target_latents: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Eq. 11 (L_SP): || z_{t+k} - z_hat_{t+k} ||^2 averaged over sampled chunk steps.

    pred_latents/target_latents (B,S,d_z) in policy latent units (target from the frozen encoder, no grad);
    the squared distance is summed over features, which the units make an RMS-scale quantity.
    """
    err = ((pred_latents.float() - target_latents.detach()) ** 2).sum(-1)
    return _masked_mean(err, mask)


def reconstruction_loss(decoded: torch.Tensor, target_images: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Decoder g: MSE between g(stop-grad z_hat) and the downsampled observed next frame (agent view)."""
    err = ((decoded.float() - target_images) ** 2).mean(dim=(-1, -2, -3))
    return _masked_mean(err, mask)


def unified_loss(model: CMSModel, out: CMSOutput, batch: dict[str, torch.Tensor],
                 cfg: LossConfig) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 8: L = L_IL + alpha * L_RL + beta * L_SP (+ the decoder's own reconstruction loss). With
    ``cfg.aux_on_trunk`` off, ``out`` comes from ``model(batch, aux_on_trunk=False)`` and L_RL is the critic's."""
    il_mask = batch["action_mask"] * batch["imitate"].unsqueeze(1)
    l_il, logs = imitation_loss(out.logits, out.continuous, batch["bins"], batch["actions"], il_mask,
                                cfg.lam, cfg.use_discrete, cfg.use_continuous)
    total = l_il
    logs["il"] = l_il.detach()
    if cfg.use_rl and cfg.alpha > 0:
        # the actor moves the continuous head, and through it the trunk: it is off when the trunk is imitation's
        l_actor = actor_loss(out.continuous, model.log_sigma, batch["actions"], batch["advantages"],
                             batch["action_mask"], cfg.actor_positive_only) if cfg.aux_on_trunk else None
        l_critic = critic_loss(out.values, out.value_now, batch["returns"], batch["value_mask"])
        l_rl = cfg.critic_coef * l_critic if l_actor is None else l_actor + cfg.critic_coef * l_critic
        logs.update(rl_critic=l_critic.detach(), **({} if l_actor is None else {"rl_actor": l_actor.detach()}))
        total = total + cfg.alpha * l_rl
        logs["rl"] = l_rl.detach()
    if cfg.use_sp or cfg.use_recon:
        idx = batch["sp_index"]
        pred = torch.gather(out.latents, 1, idx.unsqueeze(-1).expand(-1, -1, out.latents.shape[-1]))
        if cfg.use_sp and cfg.beta > 0:
            target = model.target(batch["sp_images"], batch.get("sp_proprio"))
            l_sp = state_prediction_loss(pred, target, batch["sp_mask"])
            total = total + cfg.beta * l_sp
            logs["sp"] = l_sp.detach()
        if cfg.use_recon:
            size = model.cfg.decoder_size
            frames = batch["sp_images"][:, :, 0]  # first camera (agent view), (B,S,3,H,W)
            small = F.interpolate(frames.flatten(0, 1).float(), size=(size, size),
                                  mode="area").unflatten(0, frames.shape[:2])
            l_rec = reconstruction_loss(model.decoder(pred), small, batch["sp_mask"])
            total = total + l_rec
            logs["recon"] = l_rec.detach()
    logs["total"] = total.detach()
    return total, logs
