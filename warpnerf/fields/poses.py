"""Camera pose refinement: a learned SE(3) correction per training camera (``--pose-refine``).

Camera ``k``'s rays are corrected in world space about the camera's centre: directions rotated by
``R_k = exp(omega_k)`` (axis-angle, Rodrigues' formula), origins moved by ``tau_k``. Both start at
zero (the given poses). The corrections are relative: their mean over the training cameras is
removed before they are applied, so the cameras cannot drift together (a motion of the whole
scene that the images cannot tell from the poses) away from the held-out cameras, whose given
poses are used as they are. Gradients reach the corrections through the rays' origins and
directions: the sample positions, the hash encoding's position gradient
(``hash_encode_bwd_x``) or the positional encoding, and the view directions.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["CameraCorrection", "so3_exp"]


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] of axis-angle vectors [..., 3] (Rodrigues; the Taylor series
    of sin(t)/t and (1 - cos t)/t^2 near t = 0, so the gradient at zero is exact and finite)."""
    t2 = (omega * omega).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    small = t2 < 1e-8
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = t2s.sqrt()
    a = torch.where(small, 1 - t2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(t)) / t2s)
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*omega.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a * k + b * (k @ k)


class CameraCorrection(nn.Module):
    """Per-camera rotation (axis-angle) and translation corrections, zero at the start."""

    def __init__(self, n_cameras: int):
        super().__init__()
        if not 1 <= int(n_cameras) <= 10**6:
            raise ValueError(f"n_cameras must be in [1, 10^6], got {n_cameras}")
        self.rotation = nn.Parameter(torch.zeros(int(n_cameras), 3))
        self.translation = nn.Parameter(torch.zeros(int(n_cameras), 3))

    @property
    def n_cameras(self) -> int:
        return self.rotation.shape[0]

    def corrections(self) -> tuple:
        """(axis-angle [n, 3], translation [n, 3]) as applied: their means removed."""
        return (self.rotation - self.rotation.mean(0), self.translation - self.translation.mean(0))

    def matrices(self) -> torch.Tensor:
        """[n, 4, 4] world-space corrections (rotation about the camera centre is applied by
        :meth:`forward`; as a pose: ``c2w' = [R R_c | t_c + tau]``)."""
        rot, tau = self.corrections()
        m = torch.eye(4, dtype=rot.dtype, device=rot.device).repeat(self.n_cameras, 1, 1)
        m[:, :3, :3] = so3_exp(rot)
        m[:, :3, 3] = tau
        return m

    def corrected_c2w(self, c2w: torch.Tensor) -> torch.Tensor:
        """The training cameras' refined camera-to-world matrices [n, 3|4, 4]."""
        rot, tau = self.corrections()
        c2w = c2w.clone()
        r = so3_exp(rot.to(c2w.dtype))
        c2w[:, :3, :3] = r @ c2w[:, :3, :3]
        c2w[:, :3, 3] = c2w[:, :3, 3] + tau.to(c2w.dtype)
        return c2w

    def forward(self, cam_idx: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor):
        """Corrected (origins, directions) [n, 3] of rays of training cameras ``cam_idx`` [n]
        (directions stay unit: rotated)."""
        rot, tau = self.corrections()
        r = so3_exp(rot)[cam_idx]  # [n, 3, 3]
        d = (r @ directions.unsqueeze(-1)).squeeze(-1)
        return origins + tau[cam_idx], d
