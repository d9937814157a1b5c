"""Training losses on log-depth: Eigen's scale-invariant loss + multi-scale gradient matching.

Both act on the log-ratio ``r = log(pred) - log(gt)`` over valid pixels only. A global
scale of the prediction adds a constant to ``r``: the gradient term ignores it fully, the
scale-invariant term ignores it fully for ``lam = 1`` and mostly for ``lam < 1`` (which
keeps the output near the training data's scale, in mm, without forcing it).

References: Eigen, Puhrsch & Fergus, "Depth map prediction from a single image using a
multi-scale deep network", NeurIPS 2014 (scale-invariant error); Li & Snavely, MegaDepth,
CVPR 2018 and Ranftl et al., MiDaS, TPAMI 2020 (multi-scale gradient matching).
"""

from __future__ import annotations

import torch

from chisel.core.errors import InvalidInputError


def _check(log_pred: torch.Tensor, log_gt: torch.Tensor, valid: torch.Tensor) -> None:
    if log_pred.dim() != 3 or log_pred.shape != log_gt.shape or log_pred.shape != valid.shape:
        raise InvalidInputError(
            "loss inputs",
            f"expected matching (B, H, W) log_pred, log_gt, valid; got "
            f"{tuple(log_pred.shape)}, {tuple(log_gt.shape)}, {tuple(valid.shape)}",
        )
    if valid.dtype != torch.bool:
        raise InvalidInputError("valid", f"expected a bool mask, got {valid.dtype}")


def scale_invariant_log_loss(
    log_pred: torch.Tensor, log_gt: torch.Tensor, valid: torch.Tensor, lam: float = 0.85
) -> torch.Tensor:
    """Eigen's scale-invariant log error, averaged over the images that have valid pixels.

    Per image, with ``r = log_pred - log_gt`` over its ``n`` valid pixels:
    ``L = mean(r**2) - lam * mean(r)**2``.

    Parameters
    ----------
    log_pred : (B, H, W) float, log of predicted (relative) depth.
    log_gt : (B, H, W) float, log of true depth in mm (any finite value where invalid).
    valid : (B, H, W) bool, True where the true depth is valid.
    lam : in [0, 1]; 1 = fully scale-invariant, 0 = plain mean squared log error.

    Returns a scalar tensor; 0 (still differentiable) if no pixel is valid.
    """
    _check(log_pred, log_gt, valid)
    if not 0.0 <= lam <= 1.0:
        raise InvalidInputError("lam", f"must be in [0, 1], got {lam}")
    w = valid.to(log_pred.dtype)
    r = torch.where(valid, log_pred - log_gt, torch.zeros_like(log_pred))
    n = w.sum(dim=(1, 2))
    has = n > 0
    if not bool(has.any()):
        return log_pred.sum() * 0.0
    n_safe = n.clamp(min=1.0)
    mean_r = r.sum(dim=(1, 2)) / n_safe
    mean_r2 = (r * r).sum(dim=(1, 2)) / n_safe
    per_image = mean_r2 - lam * mean_r * mean_r
    return per_image[has].mean()


def gradient_matching_loss(
    log_pred: torch.Tensor, log_gt: torch.Tensor, valid: torch.Tensor, num_scales: int = 4
) -> torch.Tensor:
    """Multi-scale gradient matching of the log-ratio (MiDaS form, on log-depth).

    At scale ``k`` the maps are subsampled by ``2**k`` (every ``2**k``-th pixel, as in
    MiDaS); with ``r = log_pred - log_gt`` the term is the sum of ``|r[x+1] - r[x]|`` over
    horizontal and vertical neighbour pairs that are both valid, divided by the number of
    such pairs. The scales are summed. Invariant to any global scale of the prediction.

    Parameters
    ----------
    log_pred, log_gt : (B, H, W) float log-depth (prediction relative, truth in mm).
    valid : (B, H, W) bool, True where the true depth is valid.
    num_scales : >= 1.

    Returns a scalar tensor; scales without a valid pair contribute 0.
    """
    _check(log_pred, log_gt, valid)
    if num_scales < 1:
        raise InvalidInputError("num_scales", f"must be >= 1, got {num_scales}")
    r_full = torch.where(valid, log_pred - log_gt, torch.zeros_like(log_pred))
    total = log_pred.sum() * 0.0
    for k in range(num_scales):
        step = 2**k
        r = r_full[:, ::step, ::step]
        v = valid[:, ::step, ::step]
        vx = v[:, :, 1:] & v[:, :, :-1]
        vy = v[:, 1:, :] & v[:, :-1, :]
        gx = torch.where(vx, (r[:, :, 1:] - r[:, :, :-1]).abs(), torch.zeros_like(r[:, :, 1:]))
        gy = torch.where(vy, (r[:, 1:, :] - r[:, :-1, :]).abs(), torch.zeros_like(r[:, 1:, :]))
        pairs = vx.sum() + vy.sum()
        if int(pairs) > 0:
            total = total + (gx.sum() + gy.sum()) / pairs.to(log_pred.dtype)
    return total


def depth_loss(
    log_pred: torch.Tensor,
    depth_gt_mm: torch.Tensor,
    valid: torch.Tensor,
    lam: float = 0.85,
    grad_weight: float = 0.5,
    num_scales: int = 4,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Training loss ``SI(lam) + grad_weight * GM(num_scales)``.

    log_pred : (B, H, W) float log relative depth. depth_gt_mm : (B, H, W) float mm,
    anything where invalid. valid : (B, H, W) bool. Returns (loss, {"si", "grad"} floats).
    """
    safe_gt = torch.where(valid, depth_gt_mm, torch.ones_like(depth_gt_mm))
    log_gt = torch.log(safe_gt)
    si = scale_invariant_log_loss(log_pred, log_gt, valid, lam)
    gm = gradient_matching_loss(log_pred, log_gt, valid, num_scales)
    return si + grad_weight * gm, {"si": float(si.detach()), "grad": float(gm.detach())}
