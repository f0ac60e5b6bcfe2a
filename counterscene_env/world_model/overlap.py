"""Overlap: how deep agents' boxes run into each other, differentiably (the training loss's
overlap term, ``loss.training_loss``; docs/history/world_model.md, "The network's own collisions").

Two oriented boxes overlap exactly when their projections overlap on each of the four axes
of the separating-axis theorem (each box's heading and its normal). The depth used here is
the smallest of those four projection overlaps, clipped at 0: the distance one box would
have to move along the best axis to clear the other [m]. It is 0 for boxes apart, grows
linearly with penetration, and its gradient moves the centres and headings apart. It is the
same test as ``geometry.boxes_overlap`` (positive exactly where that one says True), written
in torch.

:func:`new_overlaps` is the evaluation's side (``counterscene evaluate-model``): the steps at
which a prediction puts two agents on each other where the log does not.
"""

from __future__ import annotations

import numpy as np
import torch

from counterscene_env.geometry import overlaps_over_time


def penetration(xy: torch.Tensor, yaw: torch.Tensor, extents: torch.Tensor) -> torch.Tensor:
    """Pairwise box penetration depth.

    Args:
        xy: ``[..., K, 2]`` m, box centres; yaw ``[..., K]`` rad; extents ``[..., K, 2]`` m
            (length, width), broadcastable to ``xy``.

    Returns:
        ``[..., K, K]`` m, symmetric, 0 where two boxes do not overlap; the diagonal is not
        meaningful (a box overlaps itself).
    """
    h = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)  # [..., K, 2] heading
    n = torch.stack([-h[..., 1], h[..., 0]], -1)  # its normal
    half = 0.5 * extents
    axes = torch.stack([h, n], -2)  # [..., K, 2 axes, 2]
    d = xy[..., None, :, :] - xy[..., :, None, :]  # [..., K(i), K(j), 2], j's centre from i's
    # Axes of box i (rows) and of box j (columns): [..., K, K, 4, 2].
    ax = torch.cat(
        [
            axes[..., :, None, :, :].expand(*d.shape[:-1], 2, 2),
            axes[..., None, :, :, :].expand(*d.shape[:-1], 2, 2),
        ],
        -2,
    )

    def radius(heading: torch.Tensor, normal: torch.Tensor, hl: torch.Tensor) -> torch.Tensor:
        # A box's half extent projected on each axis: |h.a| L/2 + |n.a| W/2.
        return (ax * heading[..., None, :]).sum(-1).abs() * hl[..., 0, None] + (
            ax * normal[..., None, :]
        ).sum(-1).abs() * hl[..., 1, None]

    r_i = radius(h[..., :, None, :], n[..., :, None, :], half[..., :, None, :])
    r_j = radius(h[..., None, :, :], n[..., None, :, :], half[..., None, :, :])
    gap = (ax * d[..., None, :]).sum(-1).abs()  # [..., K, K, 4]
    return torch.relu(r_i + r_j - gap).amin(-1)


def overlap_loss(
    pred: torch.Tensor,
    truth: torch.Tensor,
    extents: torch.Tensor,
    ok: torch.Tensor,
) -> torch.Tensor:
    """Mean penetration [m] of the predicted boxes per valid agent-step, over the pairs whose
    logged boxes do not overlap at that step (a log's own overlaps, from imprecise real boxes,
    are not the model's to undo).

    Args:
        pred: ``[B, K, F, >=3]`` predicted x, y [m], course [rad] (a rolled-out prediction).
        truth: ``[B, K, F, >=3]`` the log's states.
        extents: ``[B, K, 2]`` m.
        ok: ``[B, K, F]`` bool, agent and step valid.
    """
    ext = extents[:, None]  # [B, 1, K, 2] for [B, F, K] boxes
    p = penetration(pred[..., :2].transpose(1, 2), pred[..., 2].transpose(1, 2), ext)
    with torch.no_grad():
        logged = penetration(truth[..., :2].transpose(1, 2), truth[..., 2].transpose(1, 2), ext)
    okt = ok.transpose(1, 2)  # [B, F, K]
    K = ok.shape[1]
    pair = okt[..., :, None] & okt[..., None, :] & (logged <= 0)
    pair &= ~torch.eye(K, dtype=torch.bool, device=ok.device)
    # Each pair counted once (the matrix is symmetric), per valid agent-step.
    return (p * pair).sum() / 2 / ok.float().sum().clamp(min=1)


def new_overlaps(
    pred: np.ndarray, truth: np.ndarray, extents: np.ndarray, ok: np.ndarray
) -> np.ndarray:
    """``[F]`` bool: at each step, two of the ``A`` agents' predicted boxes overlap while
    their logged boxes do not.

    Args:
        pred: ``[A, F, >=3]`` x, y [m], yaw [rad] predicted; truth ``[A, F, >=3]`` logged.
        extents: ``[A, 2]`` m. ok: ``[A, F]`` bool, the steps scored (both valid).
    """
    mine = overlaps_over_time(pred[..., :2], pred[..., 2], extents, ok)  # [F, A, A]
    logged = overlaps_over_time(truth[..., :2], truth[..., 2], extents, ok)
    return (mine & ~logged).any((1, 2))
