"""LBS handles as bones: the LBS solver's motion rewritten as a convex blend of affine maps
(:func:`lbs_blend_form`), each map a parent/child bone chain keyed with its continuous singular value
decomposition (:func:`continuous_svd`, :func:`chain_channels`), checked by evaluating it exactly as Blender's
Armature modifier does (:func:`armature_deform`); :func:`plan_armature` gives the :class:`ArmaturePlan` or says
why bones cannot carry the motion.

Pure numpy and scipy (one coherent algorithm).  Uses :mod:`.body` and :mod:`.output` (the default tolerance);
the Blender writer is :mod:`unipixie.core.blender_io.bake.armature`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .body import BakeObject
from .output import ARMATURE_TOLERANCE


def _safe_scale(A: np.ndarray, D: np.ndarray, margin: float = 0.5) -> float:
    """Largest s ≥ 0 (times ``margin``) such that det(A_t + s' D_t) stays positive for all s' ≤ s and all t.

    A, D: (T, 3, 3).  det(A + sD) = det A · det(I + sM), M = A⁻¹D, a cubic in s whose smallest positive
    real root is where the bone map would collapse.
    """
    try:
        M = np.linalg.solve(A, D)
    except np.linalg.LinAlgError:
        return np.inf  # a singular constant handle: refused by the caller anyway
    c1 = np.trace(M, axis1=-2, axis2=-1)
    c2 = 0.5 * (c1 ** 2 - np.trace(M @ M, axis1=-2, axis2=-1))
    c3 = np.linalg.det(M)
    # 1 + c1 s + c2 s² + c3 s³ = 0  ⇔  u³ + c1 u² + c2 u + c3 = 0 with u = 1/s (monic: batched companion eigenvalues)
    comp = np.zeros((len(M), 3, 3))
    comp[:, 0, :] = -np.stack([c1, c2, c3], axis=1)
    comp[:, 1, 0] = 1.0
    comp[:, 2, 1] = 1.0
    u = np.linalg.eigvals(comp)
    real = (np.abs(u.imag) <= 1e-9 * np.maximum(1.0, np.abs(u))) & (u.real > 0)
    if not np.any(real):
        return np.inf
    return margin / float(np.max(u.real[real]))


def lbs_blend_form(weights: np.ndarray, handle_transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Rewrite the LBS solver's motion as a convex blend of absolute affine maps (what an armature does).

    The LBS solver (:mod:`unipixie.solvers.lbs`) moves a rest point X (world metres) as
    ``x = A [X; 1] + Σ_{h<H} w_h(X) D_h [X; 1]`` with ``A = handle_transforms[:, H]`` (the constant
    handle, a full affine map) and ``D_h = handle_transforms[:, h]`` displacement maps; ``weights``
    are (N, H+1) with the last column 1.  This equals ``Σ_b ω_b(X) M_b [X; 1]`` for the bones
    ``M_const = A`` and ``M_h± = A ± k_h± D_h`` with weights ``ω_h± = w_h±(X) / k_h±`` (the positive
    and negative parts of w_h) and ``ω_const = 1 − Σ ω_h±``: weights in [0, 1] summing to 1, as
    Blender's Armature modifier needs, for any scales k with ``Σ_h w_h±/k_h± ≤ 1`` at every vertex.
    The scales are chosen as small as that allows but proportional to the largest scale at which
    each bone map stays orientation-preserving over the whole motion (half the distance to
    collapse), so that the bones are proper (rotation × stretch) maps whenever that is possible.
    Bones whose weight is zero everywhere are dropped.

    Returns ``(maps (T, B, 4, 4) world-space, bone_weights (N, B), labels)`` with labels such as
    ``"constant"``, ``"03+"``, ``"03-"``; a bone map may still have det ≤ 0 when the motion is too
    large for any choice (the caller refuses those).
    """
    W = np.asarray(weights, dtype=np.float64)
    HT = np.asarray(handle_transforms, dtype=np.float64)
    T, H1 = HT.shape[:2]
    H = H1 - 1
    if W.ndim != 2 or W.shape[1] != H1:
        raise ValueError(f"weights must be (N, {H1}), got {W.shape}")

    def affine(m):
        out = np.zeros(m.shape[:-2] + (4, 4))
        out[..., :3, :] = m
        out[..., 3, 3] = 1.0
        return out

    A = affine(HT[:, H])
    parts, limits = [], []
    for h in range(H):
        for sign in (1.0, -1.0):
            part = np.clip(sign * W[:, h], 0.0, None)
            if np.any(part > 0):
                lim = _safe_scale(A[:, :3, :3], sign * HT[:, h, :, :3])
                parts.append((h, sign, part))
                limits.append(lim if np.isfinite(lim) else None)
    finite = [x for x in limits if x is not None]
    fallback = max(finite) if finite else 1.0
    scales = np.array([x if x is not None else fallback for x in limits])
    if parts:
        load = sum(p / sc for (_, _, p), sc in zip(parts, scales))  # (N,) Σ w±/s± per vertex
        lam = float(np.max(load))
        scales = scales * max(lam, 1e-12)  # smallest scales keeping the constant weight ≥ 0
    maps = [A]
    bone_w = [np.ones(len(W))]
    labels = ["constant"]
    for (h, sign, part), k in zip(parts, scales):
        D = np.zeros((T, 4, 4))
        D[:, :3, :] = HT[:, h]
        maps.append(A + sign * k * D)
        bone_w.append(part / k)
        bone_w[0] = bone_w[0] - part / k
        labels.append(f"{h:02d}{'+' if sign > 0 else '-'}")
    return np.stack(maps, axis=1), np.clip(np.stack(bone_w, axis=1), 0.0, 1.0), labels


@dataclass
class ArmaturePlan:
    """Bones that reproduce an LBS motion in Blender's Armature modifier (object-local space).

    Each bone b of the blend (:func:`lbs_blend_form`) is a chain of two bones with the same head
    ``heads[b]`` and identity rest orientation (pointing along +Y): a non-deforming *parent* keyed
    with location ``parent_location``, rotation ``parent_rotation`` (U) and scale ``parent_scale`` (Σ),
    and a deforming *child* (inherits rotation and scale) keyed with rotation ``child_rotation``
    (Vᵀ).  Their product is ``U Σ Vᵀ``, the singular value decomposition of the bone's affine map,
    so any orientation-preserving affine map — shear and stretch along turning axes included — is
    exact at every frame.

    heads: (B, 3) object-local; quaternions are (T, B, 4) w-x-y-z; scales (T, B, 3).
    local_maps: (T, B, 4, 4) the bones' affine maps in object-local coordinates.
    weights: (N, B) float32 vertex-group weights in [0, 1], summing to 1 per vertex.
    labels: which LBS handle each bone comes from.
    max_error: largest distance (metres) between the armature's result and the trajectory.
    bone_length: display length of the bones, Blender units.
    ground_height: world z (metres) below which no vertex may go (a ground modifier after the
        Armature lifts them onto it), or None when no vertex dips below the ground.
    """

    heads: np.ndarray
    local_maps: np.ndarray
    parent_location: np.ndarray
    parent_rotation: np.ndarray
    parent_scale: np.ndarray
    child_rotation: np.ndarray
    weights: np.ndarray
    labels: list
    max_error: float
    bone_length: float
    ground_height: Optional[float] = None

    @property
    def bone_count(self) -> int:
        return int(self.heads.shape[0])


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices → (…, 4) unit quaternions (w, x, y, z), Blender's order."""
    from scipy.spatial.transform import Rotation

    shape = R.shape[:-2]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()  # x, y, z, w
    return np.concatenate([q[:, 3:4], q[:, :3]], axis=1).reshape(*shape, 4)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    shape = q.shape[:-1]
    q = q.reshape(-1, 4)
    return Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_matrix().reshape(*shape, 3, 3)


def _continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """(T, …, 4): flip signs so consecutive frames lie on one hemisphere (interpolation takes the short way)."""
    q = q.copy()
    for t in range(1, q.shape[0]):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0
        q[t][flip] *= -1.0
    return q


def continuous_svd(L: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, 3, 3) with det > 0 → (U, s, V) with L = U diag(s) Vᵀ, U and V proper rotations, s > 0, and the
    columns of V matched frame to frame (order and sign) so that the keyed rotations change smoothly."""
    import itertools

    T = L.shape[0]
    U, s, Vt = np.linalg.svd(L)
    V = np.swapaxes(Vt, -1, -2)
    fix = np.linalg.det(V) < 0  # det L > 0: det U = det V; make both proper
    V[fix, :, 2] *= -1
    U[fix, :, 2] *= -1
    perms = np.array(list(itertools.permutations(range(3))))
    rows = np.arange(3)
    for t in range(1, T):
        M = np.abs(V[t - 1].T @ V[t])
        best = perms[int(np.argmax(M[rows, perms].sum(1)))]
        V[t], U[t], s[t] = V[t][:, best], U[t][:, best], s[t][best]
        signs = np.sign(np.sum(V[t - 1] * V[t], axis=0))
        signs[signs == 0] = 1.0
        if np.prod(signs) < 0:  # keep V proper: leave the least aligned axis unflipped
            k = int(np.argmin(np.abs(np.sum(V[t - 1] * V[t], axis=0))))
            signs[k] *= -1
        V[t] *= signs
        U[t] *= signs
        if np.linalg.det(V[t]) < 0:  # an odd permutation: flip the least aligned axis of both
            k = int(np.argmin(np.abs(np.sum(V[t - 1] * V[t], axis=0))))
            V[t][:, k] *= -1
            U[t][:, k] *= -1
    return U, s, V


def chain_channels(local_maps: np.ndarray, heads: np.ndarray):
    """Pose channels of the parent/child bone chains (see :class:`ArmaturePlan`).

    local_maps: (T, B, 4, 4) object-local affine maps (det > 0); heads: (B, 3) the bones' rest heads.
    Returns parent location (T, B, 3), parent rotation (T, B, 4), parent scale (T, B, 3), child rotation (T, B, 4).
    """
    T, B = local_maps.shape[:2]
    loc = np.zeros((T, B, 3))
    scale = np.zeros((T, B, 3))
    Uq = np.zeros((T, B, 4))
    Vq = np.zeros((T, B, 4))
    for b in range(B):
        A = local_maps[:, b, :3, :3]
        U, s, V = continuous_svd(A)
        h = heads[b]
        # child: x → Vᵀ(x − h) + h; parent: y → U Σ (y − h) + h + t  ⇒  t = b + A h − h
        loc[:, b] = local_maps[:, b, :3, 3] + A @ h - h
        scale[:, b] = s
        Uq[:, b] = _quat_from_matrix(U)
        Vq[:, b] = _quat_from_matrix(np.swapaxes(V, -1, -2))
    return loc, _continuous_quaternions(Uq), scale, _continuous_quaternions(Vq)


def chain_deform(heads: np.ndarray, loc: np.ndarray, Uq: np.ndarray, scale: np.ndarray, Vq: np.ndarray) -> np.ndarray:
    """(T, B, 4, 4) deform matrices Blender builds from the chain channels (parent ∘ child, rest = Tr(head))."""
    T, B = loc.shape[:2]
    U = _matrix_from_quat(Uq)
    Vt = _matrix_from_quat(Vq)
    lin = U * scale[..., None, :] @ Vt
    out = np.zeros((T, B, 4, 4))
    out[..., :3, :3] = lin
    # x → U Σ (Vᵀ(x − h) + h − h) + h + t = lin x − lin h + h + t
    out[..., :3, 3] = -np.einsum("tbij,bj->tbi", lin, heads) + heads[None] + loc
    out[..., 3, 3] = 1.0
    return out


def armature_deform(rest_local: np.ndarray, weights: np.ndarray, deform: np.ndarray) -> np.ndarray:
    """What Blender's Armature modifier computes (linear blending, vertex groups, no preserve-volume).

    rest_local: (N, 3); weights: (N, B) ≥ 0; deform: (T, B, 4, 4) bone deform matrices
    (pose matrix × rest matrix⁻¹).  Weights are normalised per vertex; vertices with total weight
    ≤ 1e-4 stay at rest (as in Blender).  Returns (T, N, 3) float64.
    """
    x = np.asarray(rest_local, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    total = w.sum(1)
    ok = total > 1e-4
    wn = np.where(ok[:, None], w / np.where(ok, total, 1.0)[:, None], 0.0)
    T, B = deform.shape[:2]
    x1 = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    moved = np.empty((T, len(x), 3))
    for t in range(T):  # per frame: blended (N, 3, 4) matrices by one GEMM, then applied per vertex
        blended = (wn @ deform[t, :, :3, :].reshape(B, 12)).reshape(len(x), 3, 4)
        moved[t] = (blended * x1[:, None, :]).sum(-1)
    return np.where(ok[None, :, None], moved, x[None])


def plan_armature(obj: BakeObject, weights: np.ndarray, handle_transforms: np.ndarray, positions: np.ndarray,
                  tolerance: float = ARMATURE_TOLERANCE,
                  ground_height: Optional[float] = None) -> tuple[Optional[ArmaturePlan], str]:
    """Map an LBS motion to bones, or explain why it cannot be done.

    weights: (N, H+1) vertex weights (last = the constant handle); handle_transforms: (T, H+1, 3, 4)
    in the LBS solver's form (:func:`lbs_blend_form`); positions: (T, N, 3) the trajectory (world
    metres) the armature must reproduce; tolerance: allowed error as a fraction of the object's size.

    The blend's bone maps are conjugated into the object's local space (``L = S⁻¹ M S``, S the
    world-from-local matrix) and each becomes a parent/child bone chain keyed with its singular
    value decomposition (:class:`ArmaturePlan`).  Refused (``(None, reason)``) when a bone map
    mirrors or collapses space (det ≤ 0: no rotation and positive scale can make it), or when the
    motion evaluated exactly as the Armature modifier does misses the trajectory by more than
    ``tolerance × size``.

    ground_height: world z (metres) of the ground plane, or None.  The contact law lets the skinned
    surface dip into the ground between its contact samples; the solver lifts its tracked points back
    onto the plane (:mod:`unipixie.solvers.contact`), which no bone can do.  The armature's result is
    then evaluated with the same lift, done in Blender by a ground modifier after the Armature
    (``ArmaturePlan.ground_height``; set only when some vertex needs it).
    """
    W = np.asarray(weights, dtype=np.float64)
    N = obj.vertex_count
    if W.ndim != 2 or W.shape[0] != N or handle_transforms is None or W.shape[1] != np.shape(handle_transforms)[1]:
        return None, f"the skinning weights have shape {W.shape}, which does not fit {N} vertices and the handles"
    maps, bone_w, labels = lbs_blend_form(W, handle_transforms)
    S = obj.world_from_local
    L = np.linalg.inv(S) @ maps @ S
    det = np.linalg.det(L[..., :3, :3])
    if np.any(det <= 0):
        return None, ("the deformation is too large for bones: a handle's map, scaled by the range of its weights, "
                      "would mirror or collapse space, which no rotation and scale can do")
    x0 = obj.rest_local
    wsum = bone_w.sum(0)
    heads = np.where(wsum[:, None] > 1e-9, (bone_w.T @ x0) / np.maximum(wsum, 1e-12)[:, None], x0.mean(0))
    loc, Uq, scale, Vq = chain_channels(L, heads)
    moved = obj.to_world(armature_deform(x0, bone_w, chain_deform(heads, loc, Uq, scale, Vq)))
    lifted = None
    if ground_height is not None and float(moved[..., 2].min()) < ground_height:
        lifted = float(ground_height)
        np.maximum(moved[..., 2], lifted, out=moved[..., 2])
    err = float(np.max(np.linalg.norm(moved - np.asarray(positions, dtype=np.float64), axis=-1)))
    limit = tolerance * max(obj.size, 1e-12)
    if not err <= limit:
        return None, (f"the armature misses the LBS motion by {err:.3g} m (allowed {limit:.3g} m): the vertex "
                      "weights do not reproduce the solver's skinning")
    bone_length = 0.1 * float(np.max(x0.max(0) - x0.min(0)) or 1.0)
    return ArmaturePlan(heads=heads, local_maps=L, parent_location=loc, parent_rotation=Uq, parent_scale=scale,
                        child_rotation=Vq, weights=bone_w.astype(np.float32), labels=labels, max_error=err,
                        bone_length=bone_length, ground_height=lifted), ""
