"""The spring-mass solver's anchor network: anchors, springs, masses and stiffnesses of a body (:mod:`.spring_mass`).

:func:`build_network` fills the solid (:func:`fill_solid`), picks the anchors (:func:`select_anchors`, closer
together in thin parts), joins each to its nearest neighbours by springs that stay inside the solid, and gives the
:class:`AnchorNetwork` its masses, cell volumes and material; :func:`stiffness_from_youngs_modulus` and
:func:`youngs_modulus_from_stiffness` convert between a material's E (Pa) and the springs' stiffness (N/m) with
the affine-network estimate that :mod:`.spring_mass`'s docstring derives; :func:`softness_weights` is the
softness η's weakening by neighbour rank.  Units: SI (m, kg, Pa, N/m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.errors import UserError
from . import materials as materials_mod
from .body import Body
from .material_sampling import HomogeneousMaterial, MaterialSpec, sample_material
from .sampling import farthest_point_sampling, fill_mesh, thickness_at, voxel_downsample
from .scenario import Scenario
from .spring_mass_lattice import lattice_anchors, lattice_fill, lattice_springs, merge_directed
from .spring_mass_settings import DEFAULT_ANCHORS, SpringMassSettings

AFFINE_STIFFNESS_FACTOR = 12.0
"""k_i = c_E · 12 E_i V_i / Σ w_s L_s (affine network, see module docstring)."""
ANCHORS_ACROSS_THIN = 3.0
"""Anchors wanted through the thickness of thin parts (adaptive anchor sampling, :func:`select_anchors`)."""
MAX_ANCHOR_REFINEMENT = 4.0
"""Thin parts get anchors at most this many times closer together than the uniform spacing."""
NETWORK_POISSON_RATIO = 0.25
"""Poisson's ratio of an isotropic central-force network (Cauchy relation λ = μ): the springs alone."""
MIN_STAR_ISOTROPY = 0.1
"""An anchor whose spring star is flatter than this (:meth:`AnchorNetwork.star_isotropy`: its thinnest direction
carries under a tenth of its Gram matrix's largest eigenvalue, an rms thickness under ~1/3 of its length: a star in
a part fewer than about :data:`ANCHORS_ACROSS_THIN` anchors thick) gets no volumetric term and unscaled springs
(ν = 1/4 there): its least-squares F hardly measures the thickness change and G⁻¹ amplifies it ~1/isotropy times.
Measured: the canonical cube's stars (512 / 2048 anchors) lie at 0.20 / 0.23 and above, the cantilever bar's at
0.08 / 0.20 (512: under 1 % of them below 0.1); a 64-anchor 0.4 × 0.08 × 0.08 m bar's at 0.036-0.07 (46 of 64
below 0.1), a 96-anchor 0.05 m plate's all below 0.02.  With 0.05, 52 of that 64-anchor bar's anchors kept the term
and made its E/ρ refit less significant in the diagnosis (tests/test_diagnosis.py, stiffness-region case: share of
the deformation excess 0.64, springs only 0.85, with 0.1 0.81)."""
MAX_NETWORK_POISSON_RATIO = 0.45
"""Largest ν the network realises (volumetric term, :func:`poisson_split`): the term's stiffness λ − μ grows as
1/(1 − 2ν) and shortens the explicit substep with it (at ν 0.45 the P-wave modulus is 3.2 times the springs-only
network's, the substep about 0.56 of it; at 0.49 it would be 0.26); a material above it runs at this ν."""


_HELD_CLASS = np.array([materials_mod.get(int(c)).held_fixed for c in range(materials_mod.NUM_CLASSES)])
"""(classes,) bool: the material registry's held-fixed classes, by class id."""


def softness_weights(ranks: np.ndarray, neighbours: int, fixed_springs: int, softness: float) -> np.ndarray:
    """Strength factor w ∈ [0, 1] of springs of the given neighbour ranks (0 = nearest).

    ranks: (S,) int; returns (S,) float64 (see the module docstring for the formula).
    """
    r = np.asarray(ranks, dtype=np.float64)
    span = max(neighbours - fixed_springs, 1)
    if softness == -math.inf:
        return np.ones_like(r)
    base_log = np.logaddexp(0.0, softness)  # softplus(η) = log b
    t = np.clip((r - fixed_springs) / span, 0.0, None)
    w = np.clip(2.0 - np.exp(base_log * t), 0.0, 1.0)
    return np.where(r < fixed_springs, 1.0, w)


@dataclass
class AnchorNetwork:
    """The anchors and springs of one solid (everything that does not depend on the effects).

    fill_points: (F, 3) m, samples of the solid; fill_volume: (F,) m³ each; fill_cell: (F,) anchor index.
    anchors: (N, 3) m rest positions (farthest-point order for the 'farthest' layout, lattice order for 'lattice');
    volume: (N,) m³; mass: (N,) kg;
    E: (N,) Pa and nu: (N,) Poisson's ratio, cell means (over the fill points of deforming classes where the cell has
    any); material: (N,) class ids;
    pinned: (N,) bool (clamp or stationary class).
    springs: (S, 2) anchor indices (i < j); rank: (S,) int; rest_length: (S,) m.
    """

    fill_points: np.ndarray
    fill_volume: np.ndarray
    fill_cell: np.ndarray
    anchors: np.ndarray
    volume: np.ndarray
    mass: np.ndarray
    E: np.ndarray
    nu: np.ndarray
    material: np.ndarray
    pinned: np.ndarray
    springs: np.ndarray
    rank: np.ndarray
    rest_length: np.ndarray
    warnings: list

    @property
    def count(self) -> int:
        return int(len(self.anchors))

    def fabric_sums(self, weights: np.ndarray) -> np.ndarray:
        """Per anchor (Σ w L)² / ‖Σ w L d⊗d⊗d⊗d‖² · (1/5), (N,) m: the Σ w L that the least-squares fit of the
        network's affine stiffness tensor to an isotropic one divides by (module docstring).  Equal to Σ w L
        when an anchor's springs spread evenly over all directions; larger where they lie in a thin part's plane
        or along its axis (the network is stiffer along those directions than the trace says)."""
        n = self.count
        d = self.anchors[self.springs[:, 1]] - self.anchors[self.springs[:, 0]]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        wl = weights * self.rest_length
        quartic = np.einsum("si,sj,sk,sl->sijkl", d, d, d, d).reshape(len(d), 81) * wl[:, None]
        A = np.zeros((n, 81))
        np.add.at(A, self.springs[:, 0], quartic)
        np.add.at(A, self.springs[:, 1], quartic)
        swl = np.bincount(self.springs[:, 0], wl, n) + np.bincount(self.springs[:, 1], wl, n)
        return 5.0 * np.einsum("ij,ij->i", A, A) / np.maximum(swl, 1e-300)

    def star_isotropy(self) -> np.ndarray:
        """(N,) smallest over largest eigenvalue of each anchor's spring-star Gram matrix Σ_{s∋i} d_s d_sᵀ (d_s the
        spring's rest vector): 1/3-ish for a star spread through a solid, near 0 for one lying in a plane or along a
        line (a part one or two anchors thick), whose volume change it cannot measure."""
        d = self.anchors[self.springs[:, 1]] - self.anchors[self.springs[:, 0]]
        outer = d[:, :, None] * d[:, None, :]
        gram = np.zeros((self.count, 3, 3))
        np.add.at(gram, self.springs[:, 0], outer)
        np.add.at(gram, self.springs[:, 1], outer)
        ev = np.linalg.eigvalsh(gram)
        return ev[:, 0] / np.maximum(ev[:, 2], 1e-300)

    @property
    def held(self) -> np.ndarray:
        """(N,) bool: anchors of a held-fixed class (stationary: a pot, a wall), pinned whatever the scenario."""
        return _HELD_CLASS[self.material]

    def material_ends(self) -> np.ndarray:
        """(S, 2) the anchors whose stiffness, dashpot and yield each spring takes: its own two ends, except that a
        spring joining a free anchor to a held one (:attr:`held`) takes the free end's at both.  A held class never
        deforms and its E is no material's (the stationary class's is a GPa prior): the spring stands for the free
        material bonded to a rigid support.  With the held end's own, the demo plant's soil anchors on its pot got
        springs up to 6·10⁴ times the median (½ k of a GPa, clamp-sized pot cell) and alone set the substep (7.5 µs,
        docs/spring_mass.md "Performance")."""
        ends = self.springs.copy()
        held, free = self.held, ~self.pinned
        a_held = held[ends[:, 0]] & free[ends[:, 1]]
        b_held = held[ends[:, 1]] & free[ends[:, 0]]
        ends[a_held, 0] = ends[a_held, 1]
        ends[b_held, 1] = ends[b_held, 0]
        return ends

    def spring_sums(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per anchor Σ_{s∋i} w_s L_s and Σ_{s∋i} L_s, (N,) m each."""
        n = self.count
        wl = weights * self.rest_length
        swl = np.bincount(self.springs[:, 0], wl, n) + np.bincount(self.springs[:, 1], wl, n)
        sl = (np.bincount(self.springs[:, 0], self.rest_length, n)
              + np.bincount(self.springs[:, 1], self.rest_length, n))
        return swl, sl


def _solid_volume(body: Body, fallback_pts: np.ndarray) -> float:
    if body.mesh is not None and getattr(body.mesh, "is_watertight", False) and body.mesh.volume > 0:
        return float(body.mesh.volume)
    if body.mesh is not None:
        try:
            return float(body.mesh.convex_hull.volume)
        except Exception:  # degenerate hull
            pass
    ext = np.ptp(fallback_pts, axis=0)
    return float(np.prod(np.maximum(ext, 1e-9)))


def fill_solid(body: Body, target_points: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of the solid and the volume each stands for.

    Returns (F, 3) m and (F,) m³ (summing to the mesh volume for a closed mesh, or to
    ``point_volume`` × count for a point body).
    """
    target_points = int(min(max(target_points, 64), max_points))
    if body.mesh is None:
        pts = np.asarray(body.points, dtype=np.float64)
        if body.point_volume is not None:
            vol = float(body.point_volume)
            if not (np.isfinite(vol) and vol > 0):
                raise UserError(f"the body's point_volume must be a positive volume in m³, got {body.point_volume!r}")
        elif len(pts) == 1:
            raise UserError("a body of a single point needs point_volume (m³)")
        else:
            from scipy.spatial import cKDTree

            d, _ = cKDTree(pts).query(pts, k=2)
            spacing = float(np.median(d[:, 1]))
            if spacing <= 0:
                raise UserError("the body's points coincide; give distinct points or a mesh")
            vol = spacing ** 3
        return pts, np.full(len(pts), vol)
    volume = _solid_volume(body, body.rest_points)
    spacing = (volume / target_points) ** (1.0 / 3.0)
    pts = fill_mesh(body.mesh, spacing)
    # a thin solid can come back nearly empty at the first spacing: refine until it has enough points
    for _ in range(3):
        if len(pts) >= 0.25 * target_points:
            break
        spacing *= 0.5
        pts = fill_mesh(body.mesh, spacing, max_points=max(8 * max_points, 20_000_000))
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    return pts, np.full(len(pts), volume / len(pts))


def select_anchors(points: np.ndarray, count: int, pinned: np.ndarray | None = None,
                   point_volume: float | None = None, thickness: np.ndarray | None = None,
                   across: float = ANCHORS_ACROSS_THIN) -> np.ndarray:
    """Indices into ``points`` of ``count`` anchors: voxel down-sampling, then farthest-point order.

    points: (F, 3) m fill points; pinned: (F,) bool, clamped points; point_volume: m³ each; thickness: (F,) m,
    the local thickness of the part each point belongs to (:func:`~.sampling.thickness_at`).
    With ``thickness``, the sampling is adaptive: where a part is thinner than ``across`` uniform anchor
    spacings, the wanted spacing shrinks in proportion (to at most :data:`MAX_ANCHOR_REFINEMENT` times finer), so
    a trunk, a leaf or a slender bar gets about ``across`` anchors through its thickness when the count allows
    (a bending part of one or two anchors' thickness bends far too easily or not at all).
    The clamped region gets anchors only where it meets free material (within three anchor spacings of it; the
    rest of a clamp holds nothing), in proportion to that volume (at least 4 when it has them).
    """
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    count = min(int(count), n)
    vol = float(point_volume) if point_volume else None

    def thin(idx: np.ndarray, k: int) -> np.ndarray:
        if k <= 0 or len(idx) == 0:
            return np.zeros(0, dtype=np.int64)
        sub = pts[idx]
        ext = np.ptp(sub, axis=0)
        occupied = len(idx) * vol if vol else max(float(np.prod(np.maximum(ext, 1e-12))), 1e-30)
        uniform = (occupied / k) ** (1.0 / 3.0)
        if len(idx) > 8 * k:
            voxel = 0.5 * uniform if thickness is not None else (occupied / (3.0 * k)) ** (1.0 / 3.0)
            cand = voxel_downsample(sub, voxel)
            while len(cand) < 2 * k:  # the volume over-estimates sparse clouds: shrink until enough
                voxel *= 0.7
                cand = voxel_downsample(sub, voxel)
            idx = idx[cand]
            sub = pts[idx]
        spacing = None
        if thickness is not None:
            spacing = np.clip(thickness[idx] / (across * uniform), 1.0 / MAX_ANCHOR_REFINEMENT, 1.0)
        return idx[farthest_point_sampling(sub, k, spacing=spacing)]

    if pinned is None or not np.any(pinned) or np.all(pinned):
        return thin(np.arange(n), count)
    free_idx = np.flatnonzero(~pinned)
    pin_idx = np.flatnonzero(pinned)
    from scipy.spatial import cKDTree

    uniform = (len(free_idx) * (vol or 1.0) / max(count, 1)) ** (1.0 / 3.0) if vol else None
    if uniform:
        near, _ = cKDTree(pts[free_idx]).query(pts[pin_idx], distance_upper_bound=3.0 * uniform)
        pin_idx = pin_idx[np.isfinite(near)] if np.isfinite(near).sum() >= 4 else pin_idx
    n_pin = int(round(count * len(pin_idx) / (len(pin_idx) + len(free_idx))))
    n_pin = min(max(n_pin, min(4, len(pin_idx))), len(pin_idx), count - 1)
    return np.concatenate([thin(pin_idx, n_pin), thin(free_idx, count - n_pin)])


def _springs_inside(anchors: np.ndarray, springs: np.ndarray, fill: np.ndarray, fill_spacing: float) -> np.ndarray:
    """(S,) bool: springs whose segment stays inside the solid - points at ¼, ½ and ¾ of it within one fill spacing
    of a fill point.  A spring through the air between two parts (two leaves, a trunk and the pot's rim) would
    join what the solid does not."""
    from scipy.spatial import cKDTree

    tree = cKDTree(fill)
    a, b = anchors[springs[:, 0]], anchors[springs[:, 1]]
    ok = np.ones(len(springs), dtype=bool)
    for t in (0.25, 0.5, 0.75):
        d, _ = tree.query(a + t * (b - a), distance_upper_bound=fill_spacing)
        ok &= np.isfinite(d)
    return ok


MIN_MASS_RATIO = 0.6
MAX_MASS_RATIO = 2.0
"""The moment-matched masses (:func:`moment_matched_masses`) keep every anchor between these fractions of its cell's
mass; where the moments cannot be met within them the second moments are left alone (then the first moments too)."""


def _moment_rows(x: np.ndarray, second: bool) -> np.ndarray:
    """(R, n) rows of the linear map masses → (total, first moments[, second moments]) about the origin; x (n, 3)."""
    rows = [np.ones(len(x)), x[:, 0], x[:, 1], x[:, 2]]
    if second:
        rows += [x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, x[:, 0] * x[:, 1], x[:, 0] * x[:, 2], x[:, 1] * x[:, 2]]
    return np.stack(rows)


def mesh_moments(mesh) -> tuple[np.ndarray, np.ndarray] | None:
    """The centre (3,) m and the second moment per unit volume (3, 3) m² about it, ∫ r rᵀ dV / V, of a closed mesh
    (trimesh's volume integrals), or ``None`` when the mesh does not bound a volume."""
    try:
        if mesh is None or not bool(mesh.is_volume) or not float(mesh.volume) > 0:
            return None
        inertia = np.asarray(mesh.moment_inertia, dtype=np.float64) / float(mesh.volume)  # unit density, about centre
        second = 0.5 * np.trace(inertia) * np.eye(3) - inertia
        centre = np.asarray(mesh.center_mass, dtype=np.float64)
    except Exception:  # noqa: BLE001 - a mesh trimesh cannot integrate: fall back to the fill points
        return None
    if not (np.all(np.isfinite(centre)) and np.all(np.isfinite(second))):
        return None
    return centre, second


def moment_matched_masses(anchors: np.ndarray, cell_mass: np.ndarray, points: np.ndarray, point_mass: np.ndarray,
                          cell: np.ndarray, pinned: np.ndarray,
                          solid: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Anchor masses (N,) kg whose total, centre of mass and second moments (the inertia tensor) are the solid's.

    A cell's mass lumped at its anchor moves the mass outwards and off centre: the anchors are drawn by farthest-point
    sampling, so a surface anchor sits at its cell's edge, not at its centroid.  Measured on the validation's
    spinning throw (a 0.2 m cube, 192 anchors): the tracked points' centroid drifted 4 mm from an independent FEM's
    in 0.8 s, 0.3 mm at 1024 anchors, 0.1 mm with MPM (a lattice).  The masses are therefore changed as little as
    possible (Σ (m − m₀)² / m₀, m₀ the cells' masses) so that the free anchors' mass, first and second moments equal
    the solid's (10 linear conditions; Lagrange multipliers, each mass kept within bounds): ``solid``'s centre and second
    moment (:func:`mesh_moments`, exact for a closed mesh of uniform density) with the cells' total mass, else those
    of the fill points of the free anchors' cells (a lattice inside a rotated cube is off centre by a good part of
    its spacing: 1–2 mm at 192 anchors, which a spin of 3 rad/s turns into a drift of 5 mm/s); pinned anchors keep
    theirs.  Where the moments cannot be met with every mass within :data:`MIN_MASS_RATIO` … :data:`MAX_MASS_RATIO`
    of its cell's (few anchors, thin parts: a 0.6 m bar at 64 anchors) only the total and the centre of mass are
    matched, and where even they cannot, the cells' masses are kept.

    anchors: (N, 3) m; cell_mass: (N,) kg, m₀; points: (F, 3) m fill points; point_mass: (F,) kg; cell: (F,) each
    point's anchor; pinned: (N,) bool; solid: (centre (3,) m, second moment per unit mass (3, 3) m²) of the whole
    solid, used only when no anchor is pinned."""
    m0 = np.asarray(cell_mass, dtype=np.float64)
    free = ~np.asarray(pinned, dtype=bool)
    if int(free.sum()) < 16:
        return m0
    on_free = free[cell]
    w = np.asarray(point_mass, dtype=np.float64)[on_free]
    pts = np.asarray(points, dtype=np.float64)[on_free]
    if w.sum() <= 0:
        return m0
    centre = (pts * w[:, None]).sum(0) / w.sum()
    scale = max(float(np.sqrt((w[:, None] * (pts - centre) ** 2).sum() / w.sum())), 1e-12)
    x = (np.asarray(anchors, dtype=np.float64)[free] - centre) / scale
    p = (pts - centre) / scale
    mf = m0[free]
    exact = None
    if solid is not None and np.all(free):
        d = (np.asarray(solid[0], dtype=np.float64) - centre) / scale
        S = np.asarray(solid[1], dtype=np.float64) / scale ** 2 + np.outer(d, d)
        exact = mf.sum() * np.array([1.0, d[0], d[1], d[2], S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2]])
    for second in (True, False):
        A = _moment_rows(x, second)
        b = _moment_rows(p, second) @ w if exact is None else (exact if second else exact[:4])
        m = _bounded_calibration(A, b, mf)
        if m is not None:
            out = m0.copy()
            out[free] = m
            return out
    return m0


def _bounded_calibration(A: np.ndarray, b: np.ndarray, m0: np.ndarray, rounds: int = 30) -> np.ndarray | None:
    """m (n,) closest to m0 in Σ (m − m₀)²/m₀ with A m = b and MIN_MASS_RATIO m₀ ≤ m ≤ MAX_MASS_RATIO m₀, or
    ``None`` when no such m is found.  The Lagrange solution, with the masses it pushes past a bound held at the bound
    and the rest solved again (the bounded calibration of survey weights; converges in a few rounds)."""
    m = m0.copy()
    held = np.zeros(len(m0), dtype=bool)
    lo, hi = MIN_MASS_RATIO * m0, MAX_MASS_RATIO * m0
    for _ in range(rounds):
        move = ~held
        if not np.any(move):
            return None
        Am, wm = A[:, move], m0[move]
        lam = np.linalg.lstsq((Am * wm) @ Am.T, b - A[:, held] @ m[held] - Am @ wm, rcond=1e-10)[0]
        trial = wm + wm * (Am.T @ lam)
        if not np.all(np.isfinite(trial)):
            return None
        past = (trial < lo[move]) | (trial > hi[move])
        m[move] = np.clip(trial, lo[move], hi[move])
        if not np.any(past):
            break
        held[np.nonzero(move)[0][past]] = True
    ok = np.allclose(A @ m, b, rtol=1e-6, atol=1e-9 * abs(float(b[0])))
    return m if ok else None


def build_network(body: Body, material: MaterialSpec, scenario: Scenario | None = None,
                  settings: SpringMassSettings | None = None) -> AnchorNetwork:
    """Anchors, masses, cell volumes and springs of ``body`` (see the module docstring)."""
    from scipy.spatial import cKDTree

    settings = SpringMassSettings.from_any(settings)
    warnings: list[str] = []
    lattice = settings.layout == "lattice"
    if lattice:  # the symmetric layout (spring_mass_lattice.py)
        volume = _solid_volume(body, body.rest_points)
        fill, fvol, offsets, lattice_spacing = lattice_fill(body, settings.anchors, volume, settings.max_fill_points)
    else:
        fill, fvol = fill_solid(body, settings.anchors * settings.fill_per_anchor, settings.max_fill_points)
    mat = sample_material(material, fill)
    simulated = np.array([materials_mod.get(int(c)).simulated for c in range(materials_mod.NUM_CLASSES)])
    keep = simulated[mat.material]
    if not np.any(keep):
        raise UserError("the material field marks the whole solid as background (not simulated)")
    if not np.all(keep):
        warnings.append(f"{int((~keep).sum())} of {len(keep)} fill points are background material and carry no mass")
        fill, fvol = fill[keep], fvol[keep]
        if lattice:
            offsets = offsets[keep]
        mat = type(mat)(mat.E[keep], mat.nu[keep], mat.density[keep], mat.material[keep])
    held = _HELD_CLASS
    pinned_fill = held[mat.material]
    if scenario is not None:
        pinned_fill = pinned_fill | scenario.pinned_mask(fill)
    if len(fill) < 2:
        raise UserError("the solid has fewer than 2 sample points; a spring-mass network needs at least 2 anchors")
    fill_spacing = float(np.mean(fvol)) ** (1.0 / 3.0)
    if lattice:
        a_idx = lattice_anchors(fill, offsets, lattice_spacing, pinned_fill, warnings)
    else:
        thickness = thickness_at(fill, fill_spacing) if body.mesh is not None else None
        a_idx = select_anchors(fill, settings.anchors, pinned_fill, point_volume=float(np.mean(fvol)),
                               thickness=thickness)
    anchors = fill[a_idx]
    n = len(anchors)
    if n < settings.anchors and not lattice:  # a lattice has the count nearest the one asked that its cubes allow
        warnings.append(f"only {n} anchors could be placed (asked for {settings.anchors})")
    tree = cKDTree(anchors)
    _, cell = tree.query(fill)
    volume = np.bincount(cell, fvol, n)
    mass = np.bincount(cell, fvol * mat.density, n)
    # E and ν: means over the cell's fill points of the classes that deform, where it has any — a held class's E (the
    # stationary pot's GPa prior) averaged into a soil anchor's cell made its springs the pot's
    deforming = fvol * ~held[mat.material]
    own = np.bincount(cell, deforming, n)
    w = np.where(own[cell] > 0, deforming, fvol)
    w_sum = np.bincount(cell, w, n)
    if settings.mixing == "harmonic":  # the cell's materials in series (Reuss); one material: its own E
        E_cell = w_sum / np.maximum(np.bincount(cell, w / np.maximum(mat.E, 1e-300), n), 1e-300)
    else:  # in parallel (Voigt)
        E_cell = np.bincount(cell, w * mat.E, n) / np.maximum(w_sum, 1e-300)
    nu_cell = np.bincount(cell, w * mat.nu, n) / np.maximum(w_sum, 1e-300)
    # an anchor whose cell is empty (cannot happen for anchors drawn from the fill points, kept safe)
    empty = volume <= 0
    if np.any(empty):
        mean_v = float(volume[~empty].mean())
        volume[empty] = mean_v
        mass[empty] = mean_v * float(np.mean(mat.density))
        E_cell[empty] = float(np.mean(mat.E))
        nu_cell[empty] = float(np.mean(mat.nu))
    a_mat = mat.material[a_idx]
    pinned = pinned_fill[a_idx]
    uniform = bool(np.all(keep)) and float(np.ptp(mat.density)) <= 1e-9 * float(np.max(mat.density))
    solid = mesh_moments(body.mesh) if body.mesh is not None and uniform else None
    mass = moment_matched_masses(anchors, mass, fill, fvol * mat.density, cell, pinned, solid)
    # springs: directed k-NN merged into undirected pairs with the lower rank
    if lattice:  # ties at the cut-off and within a shell broken by neither index nor order
        springs, rank = lattice_springs(anchors, settings.neighbours)
    else:
        k = min(settings.neighbours, n - 1)
        _, nn = tree.query(anchors, k=k + 1)
        nn = np.asarray(nn).reshape(n, k + 1)
        src = np.repeat(np.arange(n), k)
        dst = nn[:, 1:].reshape(-1)
        rank = np.tile(np.arange(k), n)
        ok = dst != src  # duplicates of a point can return itself later in the list
        springs, rank = merge_directed(src[ok], dst[ok], rank[ok])
    if body.mesh is not None:  # no springs through the air between parts; every anchor keeps its nearest three
        inside = _springs_inside(anchors, springs, fill, fill_spacing) | (rank < 3)
        if not np.all(inside):
            warnings.append(f"{int((~inside).sum())} of {len(springs)} springs would cross empty space and were left out")
        springs, rank = springs[inside], rank[inside]
    rest = np.linalg.norm(anchors[springs[:, 1]] - anchors[springs[:, 0]], axis=1)
    if np.any(rest <= 0):
        raise UserError("two anchors coincide (duplicate points in the body); remove duplicate points")
    return AnchorNetwork(fill, fvol, cell, anchors, volume, mass, E_cell, nu_cell, a_mat, pinned, springs, rank, rest, warnings)


def anchor_positions(body: Body, anchors: int = DEFAULT_ANCHORS, scenario: Scenario | None = None) -> np.ndarray:
    """(N_a, 3) m rest positions of the anchors in the order the spring head's stiffnesses refer to.

    The anchors depend on the geometry (and the clamp), not on the material.
    """
    mat = HomogeneousMaterial(1e5, 0.3, 1000.0)
    return build_network(body, mat, scenario, SpringMassSettings(anchors=anchors)).anchors


def stiffness_from_youngs_modulus(network: AnchorNetwork, E: np.ndarray, settings: SpringMassSettings) -> np.ndarray:
    """Per-anchor stiffness k (N_a,) newtons that makes the network's modulus E (N_a,) Pa (module docstring)."""
    w = softness_weights(network.rank, settings.neighbours, settings.fixed_springs, settings.softness)
    swl = network.fabric_sums(w)
    if np.any(swl <= 0):
        raise UserError("the softness weakens every spring of some anchor to zero; lower the softness η")
    return settings.stiffness_calibration * AFFINE_STIFFNESS_FACTOR * np.asarray(E, np.float64) * network.volume / swl


def youngs_modulus_from_stiffness(network: AnchorNetwork, k: np.ndarray, settings: SpringMassSettings) -> np.ndarray:
    """Inverse of :func:`stiffness_from_youngs_modulus`: the modulus (N_a,) Pa a stiffness vector stands for."""
    w = softness_weights(network.rank, settings.neighbours, settings.fixed_springs, settings.softness)
    swl = network.fabric_sums(w)
    return np.asarray(k, np.float64) * swl / (settings.stiffness_calibration * AFFINE_STIFFNESS_FACTOR * network.volume)


def poisson_split(nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How the network realises Poisson's ratio ν (N,): (spring factor (N,), λ_extra / E (N,)).

    The springs give λ = μ (ν = 1/4); scaled by 1.25 / (1 + ν) on the E calibration they give the material's
    shear modulus μ = E / (2(1 + ν)), and the volumetric term per anchor (:mod:`.spring_mass`, energy
    ½ λ_extra V (J − 1)²) adds λ_extra = λ − μ = E (4ν − 1) / (2(1 + ν)(1 − 2ν)), so the network has the
    material's (E, ν).  ν is first clipped to [1/4, :data:`MAX_NETWORK_POISSON_RATIO`]: below 1/4, λ_extra would
    be negative (a network of pair springs cannot have λ < μ); such material runs as today's springs-only network
    (its E right, ν = 1/4).  Dimensionless.
    """
    v = np.clip(np.asarray(nu, np.float64), NETWORK_POISSON_RATIO, MAX_NETWORK_POISSON_RATIO)
    factor = (1.0 + NETWORK_POISSON_RATIO) / (1.0 + v)
    lam_extra = (4.0 * v - 1.0) / (2.0 * (1.0 + v) * (1.0 - 2.0 * v))
    return factor, lam_extra


def p_wave_per_e(nu: np.ndarray) -> np.ndarray:
    """(N,) M / E = (1 − ν) / ((1 + ν)(1 − 2ν)), the P-wave modulus per unit E of the network at the ν (N,) it
    realises (clipped as in :func:`poisson_split`)."""
    return materials_mod.elastic_p_wave_per_e(np.clip(np.asarray(nu, np.float64), NETWORK_POISSON_RATIO,
                                                      MAX_NETWORK_POISSON_RATIO))
