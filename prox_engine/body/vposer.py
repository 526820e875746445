"""VPoser v1.0, the learned pose prior of SMPLify-X and PROX, from the user's own snapshot.

The body pose becomes a 32-d code ``z``: the decoder (two 512-unit layers with leaky ReLU,
then a 6-d rotation per joint made orthonormal by Gram-Schmidt) gives the 21 body-joint
rotations, and the prior is ``|z|^2``. The encoder (batch-normalised, evaluation mode) turns
a starting posture into its code. The weights are the user's (``vposer_v1_0/snapshots/*.pt``,
a plain state dict); nothing of the licensed package is used or installed.
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch.nn import functional as F

from ..errors import InputError

LATENT, JOINTS = 32, 21
_SLOPE = 0.2
SNAPSHOT_SHAPES = {  # name -> shape (None: the hidden width, 512 in the released snapshot)
    "bodyprior_dec_fc1.weight": (None, LATENT), "bodyprior_dec_fc1.bias": (None,),
    "bodyprior_dec_fc2.weight": (None, None), "bodyprior_dec_fc2.bias": (None,),
    "bodyprior_dec_out.weight": (JOINTS * 6, None), "bodyprior_dec_out.bias": (JOINTS * 6,),
    "bodyprior_enc_bn1.weight": (JOINTS * 3,), "bodyprior_enc_bn1.bias": (JOINTS * 3,),
    "bodyprior_enc_bn1.running_mean": (JOINTS * 3,),
    "bodyprior_enc_bn1.running_var": (JOINTS * 3,),
    "bodyprior_enc_fc1.weight": (None, JOINTS * 3), "bodyprior_enc_fc1.bias": (None,),
    "bodyprior_enc_bn2.weight": (None,), "bodyprior_enc_bn2.bias": (None,),
    "bodyprior_enc_bn2.running_mean": (None,), "bodyprior_enc_bn2.running_var": (None,),
    "bodyprior_enc_fc2.weight": (None, None), "bodyprior_enc_fc2.bias": (None,),
    "bodyprior_enc_mu.weight": (LATENT, None), "bodyprior_enc_mu.bias": (LATENT,),
}


def snapshot_file(path: Path | str) -> Path:
    """The ``.pt`` file itself, or the newest ``snapshots/*.pt`` of a VPoser folder."""
    path = Path(path)
    if path.is_dir():
        snapshots = sorted((path / "snapshots").glob("*.pt")) or sorted(path.glob("*.pt"))
        if not snapshots:
            raise InputError(path, "no VPoser snapshot (expected snapshots/*.pt, as in "
                                   "vposer_v1_0)")
        return snapshots[-1]
    if not path.is_file():
        raise InputError(path, "VPoser snapshot not found")
    return path


class VPoser(torch.nn.Module):
    """Decoder and encoder of VPoser v1.0 with the user's weights."""

    def __init__(self, state: dict[str, torch.Tensor], path: Path) -> None:
        super().__init__()
        hidden = state.get("bodyprior_dec_fc1.weight", torch.zeros(0, 0)).shape[0]
        for name, shape in SNAPSHOT_SHAPES.items():
            if name not in state:
                raise InputError(path, f"'{name}' missing: not a VPoser v1.0 snapshot")
            wanted = tuple(hidden if s is None else s for s in shape)
            if tuple(state[name].shape) != wanted:
                raise InputError(path, f"'{name}' has shape {tuple(state[name].shape)}, "
                                       f"expected {wanted}")
            self.register_buffer(name.replace(".", "_"), state[name].float())

    @classmethod
    def load(cls, path: Path | str) -> VPoser:
        path = snapshot_file(path)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types for foreign files
            raise InputError(path, f"not a readable PyTorch state dict ({exc})") from exc
        if not isinstance(state, dict):
            raise InputError(path, "not a state dict")
        return cls(state, path)

    def _linear(self, name: str, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, getattr(self, f"{name}_weight"), getattr(self, f"{name}_bias"))

    def _batch_norm(self, name: str, x: torch.Tensor) -> torch.Tensor:
        return F.batch_norm(x, getattr(self, f"{name}_running_mean"),
                            getattr(self, f"{name}_running_var"),
                            getattr(self, f"{name}_weight"), getattr(self, f"{name}_bias"),
                            training=False)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 32) codes -> (B, 21, 3, 3) body-joint rotations."""
        x = F.leaky_relu(self._linear("bodyprior_dec_fc1", z), _SLOPE)
        x = F.leaky_relu(self._linear("bodyprior_dec_fc2", x), _SLOPE)
        six = self._linear("bodyprior_dec_out", x).view(-1, 3, 2)
        b1 = F.normalize(six[..., 0], dim=-1)
        b2 = F.normalize(six[..., 1] - (b1 * six[..., 1]).sum(-1, keepdim=True) * b1, dim=-1)
        rotations = torch.stack([b1, b2, torch.linalg.cross(b1, b2)], -1)
        return rotations.view(z.shape[0], JOINTS, 3, 3)

    def encode(self, pose: torch.Tensor) -> torch.Tensor:
        """(B, 21, 3) axis-angle poses -> (B, 32) codes (the posterior means)."""
        x = self._batch_norm("bodyprior_enc_bn1", pose.reshape(pose.shape[0], -1))
        x = F.leaky_relu(self._linear("bodyprior_enc_fc1", x), _SLOPE)
        x = self._batch_norm("bodyprior_enc_bn2", x)
        x = F.leaky_relu(self._linear("bodyprior_enc_fc2", x), _SLOPE)
        return self._linear("bodyprior_enc_mu", x)
