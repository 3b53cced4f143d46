"""The spring-mass network's *lattice* layout: anchors and springs that keep the body's mirror symmetries.

Farthest-point sampling (the default layout, :func:`.spring_mass_network.select_anchors`) lays the anchors
unevenly: a dense skin on the outermost fill layer, uneven layers below it, and no two sides alike.  A solid whose
motion should stay symmetric then does not: a cube dropped flat onto a frictionless floor, which the continuum
(and the independent referee, and MPM on its grid) lands without turning, leaves its first impact spinning at
0.07–0.5 rad/s (192–2048 anchors) and is tilted 5–30° by its third (docs/spring_mass.md, "The lattice layout").
The floor pushes a network whose stiffness is not spread evenly off-centre.

Here the solid is filled on a cubic lattice centred on the body's bounding box, with an odd number of points along
each axis, and every third lattice point along each axis, counted from the centre, is an anchor
(:func:`lattice_fill`, :func:`lattice_anchors`).  Every mirror plane of the box through its centre then maps
fill points onto fill points and anchors onto anchors, and no fill point is equidistant from two anchors (each
lies at most one fill spacing from its own anchor and at least two from any other along that axis), so the cells
are mirror images too.  The springs join each anchor to its ``k`` nearest and to every anchor exactly as far as
the k-th (:func:`lattice_springs`: a tie at the cut-off is broken by neither index nor order), and a spring's rank
is the number of neighbours strictly closer (a shell of equal distances shares one rank, and so one softness
weight).  Inside a cubic lattice the 32 nearest neighbours are exactly its first four shells (6 + 12 + 8 + 6).

What the layout cannot do: adapt to thin parts (a part thinner than the anchor spacing has no anchor of its own and
is carried by the nearest ones; :func:`lattice_anchors` warns), or serve the model's spring head, whose
stiffnesses are one per anchor of the farthest-point layout.  Units: SI (m, m³).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import UserError
from .sampling import inside_mesh
from .spring_mass_settings import LATTICE_STEP

_INSIDE_SHRINK = 1e-5
"""A lattice point is tested for being inside at this fraction closer to the centre: a point on a face of the body
counts as inside on both sides of a mirror plane alike, not as the ray test happens to round it."""
_SPACING_ITERATIONS = 8
_BOX_POINTS_FACTOR = 8
"""Lattice points tested in the bounding box, at most this many times ``max_fill_points``: a solid that fills less
than an eighth of its box at the fill spacing is refused rather than tested point by point."""
_CLAMP_REACH = 1.8
"""Anchor spacings: a pinned lattice anchor is kept when a free one lies this near (face, edge and corner
neighbours: 1, 1.41 and 1.73 spacings)."""
_LONELY = math.sqrt(3.0)
"""Anchor spacings: a fill point farther than a lattice cell's diagonal from every anchor lies in a part the lattice
missed (the corner of a box whose size is not a multiple of the spacing is at most this far)."""
_TIE = 1e-9
"""Distances within this fraction of the body's size are equal (lattice shells, the k-th neighbour's ties)."""


def _centre_and_half(body) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(body.mesh.bounds[0], np.float64), np.asarray(body.mesh.bounds[1], np.float64)
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _lattice_inside(mesh, centre: np.ndarray, spacing: float, half: np.ndarray,
                    max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) int offsets j and (P, 3) m points centre + j·spacing inside ``mesh``, |j_d| ≤ ⌈half_d / spacing⌉;
    refuses (UserError) a lattice of more than ``max_points`` points in the bounding box."""
    reach = np.ceil(half / spacing - 1e-9).astype(np.int64)
    total = float(np.prod(2.0 * reach + 1.0))
    if total > max_points:
        raise UserError(f"the spring-mass lattice would need {total:,.0f} points in the body's bounding box at a "
                        f"spacing of {1e3 * spacing:.3g} mm (limit {max_points:,}): the solid fills little of its box "
                        "(its volume is small for its size: thin or open parts); use layout 'farthest' or fewer "
                        "anchors")
    axes = [np.arange(-r, r + 1) for r in reach]
    offsets = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    points = centre + offsets * spacing
    inside = inside_mesh(mesh, centre + (points - centre) * (1.0 - _INSIDE_SHRINK))
    return offsets[inside], points[inside]


def lattice_fill(body, anchors: int, volume: float,
                 max_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Fill points of the solid on a lattice centred on its bounding box, spaced so that about ``anchors`` of its
    every-third points lie inside.

    body: a :class:`~.body.Body` with a closed mesh; volume: m³, the solid's volume (each fill point stands for an
    equal share).  Returns (F, 3) m points, (F,) m³ volumes, (F, 3) int lattice offsets from the centre (the
    anchors are the points whose offsets are all multiples of :data:`LATTICE_STEP`) and the anchor spacing (m).
    """
    if body.mesh is None:
        raise UserError("the spring-mass 'lattice' layout needs a closed mesh (a body of points has no inside to lay "
                        "a lattice in); use layout 'farthest'")
    centre, half = _centre_and_half(body)
    if not np.all(half > 0):
        raise UserError("the spring-mass 'lattice' layout needs a solid with extent along all three axes")
    if not (np.isfinite(volume) and volume > 0):
        raise UserError(f"the spring-mass 'lattice' layout needs a solid of positive volume, got {volume!r} m³ (an "
                        "open or inside-out mesh?); use layout 'farthest'")
    target = max(int(anchors), 2)
    box_limit = int(_BOX_POINTS_FACTOR * max_points)
    spacing = (volume / target) ** (1.0 / 3.0)
    best = None
    for _ in range(_SPACING_ITERATIONS):  # the count inside is a step function of the spacing: a few secant steps
        count = len(_lattice_inside(body.mesh, centre, spacing, half, box_limit)[0])
        if best is None or abs(count - target) < abs(best[1] - target):
            best = (spacing, count)
        if count == 0:
            spacing *= 0.5
            continue
        if abs(count - target) <= 0.02 * target:
            break
        spacing *= (count / target) ** (1.0 / 3.0)
    spacing, count = best
    if count > 0:  # within the count's range of spacings, the one whose cells share the volume evenly (cell-centred)
        even = (volume / count) ** (1.0 / 3.0)
        if len(_lattice_inside(body.mesh, centre, even, half, box_limit)[0]) == count:
            spacing = even
    fill_spacing = spacing / LATTICE_STEP
    offsets, points = _lattice_inside(body.mesh, centre, fill_spacing, half, box_limit)
    if len(points) > max_points:
        raise UserError(f"the spring-mass lattice of {anchors:,} anchors has {len(points):,} fill points, more than "
                        f"max_fill_points = {max_points:,}; give fewer anchors or raise max_fill_points")
    if len(points) < 2:
        raise UserError("the solid is thinner than the spring-mass lattice's spacing everywhere; give more anchors or "
                        "use layout 'farthest'")
    return points, np.full(len(points), volume / len(points)), offsets, spacing


def lattice_anchors(fill: np.ndarray, offsets: np.ndarray, spacing: float, pinned: np.ndarray,
                    warnings: list) -> np.ndarray:
    """Indices into ``fill`` (F, 3) m of the lattice layout's anchors: the points whose lattice ``offsets`` (F, 3)
    are multiples of :data:`LATTICE_STEP` (``spacing`` m apart).  Of the ``pinned`` (F,) bool ones (a clamp, a held
    class) only those next to a free anchor are kept (the rest of a clamp holds nothing).  Appends a warning to
    ``warnings`` where fill points lie farther than a lattice cell's diagonal from every anchor (a part thinner than
    the lattice)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(fill, np.float64)
    pinned = np.asarray(pinned, dtype=bool)
    idx = np.flatnonzero(np.all(np.asarray(offsets) % LATTICE_STEP == 0, axis=1))
    free, held = idx[~pinned[idx]], idx[pinned[idx]]
    if len(free) and len(held):
        near, _ = cKDTree(pts[free]).query(pts[held], distance_upper_bound=_CLAMP_REACH * spacing)
        idx = np.sort(np.concatenate([free, held[np.isfinite(near)]]))
    if len(idx) < 2:
        raise UserError(f"only {len(idx)} spring-mass lattice anchor(s) fit inside the solid; give more anchors or use "
                        "layout 'farthest'")
    far, _ = cKDTree(pts[idx]).query(pts)
    lonely = int(np.sum(far > _LONELY * spacing))
    if lonely:
        warnings.append(f"{lonely} of {len(pts)} fill points lie farther than a lattice cell's diagonal "
                        f"({1e3 * _LONELY * spacing:.3g} mm) "
                        "from every anchor of the spring-mass lattice: parts thinner than the spacing have no anchor "
                        "of their own (more anchors, or layout 'farthest', which refines thin parts)")
    return idx


def lattice_springs(anchors: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Undirected springs (S, 2) int64 and their ranks (S,) int64 of the lattice layout's anchors (N, 3) m.

    Each anchor is joined to its ``neighbours`` nearest and to every other anchor as near as the last of them (a
    tie at the cut-off includes the whole shell); a directed spring's rank is the number of the anchor's
    neighbours strictly closer, and an undirected spring takes the lower of its two ranks.
    """
    from scipy.spatial import cKDTree

    x = np.asarray(anchors, np.float64)
    n = len(x)
    k = min(int(neighbours), n - 1)
    if k < 1:
        raise UserError("a spring-mass network needs at least 2 anchors")
    tol = _TIE * float(np.max(np.ptp(x, axis=0)))
    tree = cKDTree(x)
    d, _ = tree.query(x, k=k + 1)
    lists = tree.query_ball_point(x, np.asarray(d)[:, -1] + tol)
    counts = np.array([len(a) for a in lists], dtype=np.int64)
    src = np.repeat(np.arange(n), counts)
    dst = np.concatenate([np.asarray(a, dtype=np.int64) for a in lists])
    keep = dst != src
    src, dst = src[keep], dst[keep]
    dist = np.linalg.norm(x[dst] - x[src], axis=1)
    order = np.lexsort((dist, src))
    src, dst, dist = src[order], dst[order], dist[order]
    start = np.searchsorted(src, src, side="left")  # each row's first entry
    new_shell = np.ones(len(src), dtype=bool)
    new_shell[1:] = (src[1:] != src[:-1]) | (dist[1:] - dist[:-1] > tol)
    rank = np.maximum.accumulate(np.where(new_shell, np.arange(len(src)), 0)) - start
    return merge_directed(src, dst, rank)


def merge_directed(src: np.ndarray, dst: np.ndarray, rank: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed neighbour pairs (src → dst, with their ranks) merged into undirected springs (S, 2) int64, each with
    the lower of its ranks (S,) int64 (Newton's third law: one spring per pair)."""
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    order = np.lexsort((rank, hi, lo))
    lo, hi, rank = lo[order], hi[order], np.asarray(rank)[order]
    first = np.ones(len(lo), dtype=bool)
    first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    return np.stack([lo[first], hi[first]], axis=1).astype(np.int64), rank[first].astype(np.int64)


def lattice_surface_points(mesh, fill: np.ndarray) -> np.ndarray:
    """(Q, 3) m points on the surface of ``mesh`` nearest to the outermost of the lattice's ``fill`` points (F, 3)
    m (those with fewer than six lattice neighbours): the contact cells' surface samples of the lattice layout.

    Random even sampling of the surface (the farthest layout's) would give mirror-image cells different lowest
    points, and a cube dropped flat would leave the floor turning (0.002–0.009 rad/s, docs/spring_mass.md); nearest
    points on the surface are mirror images of each other wherever the fill points are.
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(fill, np.float64)
    if len(pts) < 2:
        return np.zeros((0, 3))
    tree = cKDTree(pts)
    spacing = float(np.min(tree.query(pts, k=2)[0][:, 1]))
    neighbours = tree.query_ball_point(pts, spacing * (1.0 + 1e-6), return_length=True) - 1
    outer = pts[neighbours < 6]
    if len(outer) == 0:
        return np.zeros((0, 3))
    closest, _, _ = mesh.nearest.on_surface(outer)
    return np.asarray(closest, np.float64)

