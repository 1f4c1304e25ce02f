"""The evidential head and loss of EvSemSeg (docs/algorithm.md §1.2-1.3), numerically stable.

evidence = exp(clamp(logit, -c, c)), alpha = evidence + 1, S = sum alpha, p = alpha / S, u = K / S.
Loss per pixel: log S - log alpha_gt (the EDL "log" loss) + lambda * KL(Dir(alpha~) || Dir(1)), where
alpha~ = alpha with the true class's evidence removed; lambda = 0.5 * min(1, epoch / E) (paper) or
0.5 * epoch / 60 unclamped (released code).
"""

from __future__ import annotations

import torch


def dirichlet_from_logits(logits: torch.Tensor, clamp: float = 10.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """alpha [B, K, ...], probabilities alpha / S, uncertainty u = K / S [B, ...]."""
    alpha = torch.exp(torch.clamp(logits, -clamp, clamp)) + 1.0
    total = alpha.sum(dim=1, keepdim=True)
    return alpha, alpha / total, logits.shape[1] / total.squeeze(1)


def kl_to_uniform_dirichlet(alpha: torch.Tensor) -> torch.Tensor:
    """KL(Dir(alpha) || Dir(1, ..., 1)) over dim 1."""
    k = alpha.shape[1]
    total = alpha.sum(dim=1)
    return (torch.lgamma(total) - torch.lgamma(torch.tensor(float(k), dtype=alpha.dtype, device=alpha.device))
            - torch.lgamma(alpha).sum(dim=1)
            + ((alpha - 1.0) * (torch.digamma(alpha) - torch.digamma(total).unsqueeze(1))).sum(dim=1))


def kl_weight(epoch: int, anneal_epochs: int, schedule: str = "paper", strength: float = 0.5) -> float:
    """lambda for a 1-based epoch: paper 0.5 min(1, epoch / E); release 0.5 epoch / 60, unclamped."""
    if schedule == "paper":
        return strength * min(1.0, epoch / max(anneal_epochs, 1))
    if schedule == "release":
        return strength * epoch / 60.0
    raise ValueError(f"KL schedule must be 'paper' or 'release', got {schedule!r}")


def edl_loss(logits: torch.Tensor, target: torch.Tensor, kl_lambda: float, clamp: float = 10.0,
             ignore_index: int | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean over (non-ignored) pixels of the log loss plus kl_lambda times the mean KL term."""
    alpha, _, _ = dirichlet_from_logits(logits, clamp)
    valid = torch.ones_like(target, dtype=torch.bool) if ignore_index is None else target != ignore_index
    safe_target = torch.where(valid, target, torch.zeros_like(target))
    onehot = torch.nn.functional.one_hot(safe_target, alpha.shape[1]).movedim(-1, 1).to(alpha.dtype)
    log_loss = torch.log(alpha.sum(dim=1)) - torch.log((alpha * onehot).sum(dim=1))
    alpha_tilde = (alpha - 1.0) * (1.0 - onehot) + 1.0
    kl = kl_to_uniform_dirichlet(alpha_tilde)
    n = valid.sum().clamp(min=1)
    log_mean = (log_loss * valid).sum() / n
    kl_mean = (kl * valid).sum() / n
    return log_mean + kl_lambda * kl_mean, {"log_loss": float(log_mean.detach()), "kl": float(kl_mean.detach())}
