"""Sparse voxel batches and their patch-token layout.

The model never sees a dense R³×D feature tensor.  A batch of B objects is
the concatenation of their occupied voxels (:class:`VoxelBatch`), and the
decoders' tokens are the occupied P³ patches of each object
(:class:`PatchLayout`): a patch token carries the P³ voxels inside it, with
a slot mask marking which of them are occupied.  Unoccupied slots are zero
in every token input, excluded from every loss and dropped from every
output; objects with fewer patches than the largest in the batch are padded
with invalid tokens, which the decoders never mix with valid ones (decoder
tokens attend only to the latents, never to each other).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import UserError


@dataclass
class VoxelBatch:
    """Occupied voxels of B objects.

    voxels: (N, 4) int64 rows ``[sample, i, j, k]``, grouped by sample, each sample in the C order of
        ``np.argwhere(occupancy)`` (the row order of :class:`~unipixie.core.types.FeatureGrid.features`).
    features: (N, D) float tensor, the per-voxel input features.
    batch_size: B.
    resolution: R, voxels per side.
    """

    voxels: torch.Tensor
    features: torch.Tensor
    batch_size: int
    resolution: int

    @property
    def sample(self) -> torch.Tensor:
        return self.voxels[:, 0]

    @property
    def counts(self) -> torch.Tensor:
        """(B,) occupied voxels per sample."""
        return torch.bincount(self.sample, minlength=self.batch_size)

    def to(self, device) -> "VoxelBatch":
        return VoxelBatch(self.voxels.to(device), self.features.to(device), self.batch_size, self.resolution)

    @classmethod
    def from_grids(cls, occupancies, features, device="cpu") -> "VoxelBatch":
        """Build from B (R, R, R) bool occupancies and their (K_b, D) feature rows (numpy)."""
        if not occupancies:
            raise UserError("empty batch: no objects given")
        R = int(occupancies[0].shape[0])
        rows, feats = [], []
        for b, (occ, f) in enumerate(zip(occupancies, features)):
            idx = np.argwhere(np.asarray(occ, bool))
            if idx.shape[0] == 0:
                raise UserError(f"object {b} of the batch has no occupied voxels")
            if np.asarray(occ).shape != (R, R, R):
                raise UserError(f"object {b}: occupancy is {np.asarray(occ).shape}, the batch uses {(R, R, R)}")
            rows.append(np.concatenate([np.full((idx.shape[0], 1), b), idx], axis=1))
            feats.append(np.asarray(f, dtype=np.float32))
        voxels = torch.from_numpy(np.concatenate(rows).astype(np.int64))
        return cls(voxels.to(device), torch.from_numpy(np.concatenate(feats)).to(device), len(occupancies), R)


class PatchLayout:
    """Occupied P³ patches of a :class:`VoxelBatch` as padded decoder tokens.

    Attributes (all tensors on the batch's device):

    token_valid: (B, T) bool, true for real (non-padding) tokens; T = most patches of any sample.
    slot_mask: (B, T, P³) bool, true for occupied voxel slots.
    centres: (B, T, 3) float32 patch centres in [0, 1]³ (grid coordinates / R).
    sample_index, token_index, slot_index: (N,) int64, where each voxel of the batch sits.
    """

    def __init__(self, voxels: torch.Tensor, batch_size: int, resolution: int, patch_size: int):
        P, R = int(patch_size), int(resolution)
        if R % P:
            raise UserError(f"grid resolution {R} is not a multiple of the patch size {P}")
        G = R // P
        self.patch_size, self.resolution, self.batch_size = P, R, int(batch_size)
        b = voxels[:, 0]
        ijk = voxels[:, 1:]
        coarse = torch.div(ijk, P, rounding_mode="floor")
        fine = ijk - coarse * P
        slot = (fine[:, 0] * P + fine[:, 1]) * P + fine[:, 2]
        key = ((b * G + coarse[:, 0]) * G + coarse[:, 1]) * G + coarse[:, 2]
        uniq, inverse = torch.unique(key, sorted=True, return_inverse=True)
        patch_sample = torch.div(uniq, G ** 3, rounding_mode="floor")
        counts = torch.bincount(patch_sample, minlength=self.batch_size)
        starts = torch.cumsum(counts, 0) - counts
        position = torch.arange(uniq.shape[0], device=voxels.device) - starts[patch_sample]
        T = max(int(counts.max().item()) if counts.numel() else 1, 1)
        self.tokens = T
        self.sample_index = b
        self.token_index = position[inverse]
        self.slot_index = slot
        self.token_valid = torch.zeros(self.batch_size, T, dtype=torch.bool, device=voxels.device)
        self.token_valid[patch_sample, position] = True
        self.slot_mask = torch.zeros(self.batch_size, T, P ** 3, dtype=torch.bool, device=voxels.device)
        self.slot_mask[b, self.token_index, slot] = True
        cell = uniq - patch_sample * G ** 3
        cz = cell % G
        cy = torch.div(cell, G, rounding_mode="floor") % G
        cx = torch.div(cell, G * G, rounding_mode="floor")
        centres = torch.zeros(self.batch_size, T, 3, device=voxels.device)
        centres[patch_sample, position] = (torch.stack([cx, cy, cz], dim=-1).float() + 0.5) * (P / R)
        self.centres = centres

    @property
    def slots(self) -> int:
        return self.patch_size ** 3

    def to_tokens(self, values: torch.Tensor) -> torch.Tensor:
        """(N, ch) per-voxel values -> (B, T, P³, ch) with zeros at unoccupied slots and padding tokens."""
        out = values.new_zeros(self.batch_size, self.tokens, self.slots, values.shape[-1])
        out[self.sample_index, self.token_index, self.slot_index] = values
        return out

    def from_tokens(self, tokens: torch.Tensor) -> torch.Tensor:
        """(B, T, P³, ch) -> (N, ch): the occupied voxels' values, in the batch's voxel order."""
        return tokens[self.sample_index, self.token_index, self.slot_index]

    def from_tokens_single(self, tokens: torch.Tensor) -> torch.Tensor:
        """For a one-object layout: (A, T, P³, ch) with A variants (α values) -> (A, N, ch)."""
        if self.batch_size != 1:
            raise ValueError("from_tokens_single needs a layout of one object")
        return tokens[:, self.token_index, self.slot_index]
