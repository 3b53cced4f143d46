"""Measured motion of tracked points: the ``unipixie.measurement/1`` file and its CSV variant.

The contract is ``shared/specs/measurement-format.md`` §1.  A measurement is

* ``positions``: (T, N, 3) float64 metres; NaN marks a point not observed at an instant
  (occlusion).  A sample with any NaN coordinate counts as unobserved as a whole and is
  skipped in every error, never treated as zero;
* ``times``: (T,) float64 seconds, strictly increasing; ``times[0]`` is the initial state;
* ``rest_positions``: (N, 3) metres, the undeformed state (default ``positions[0]``);
* ``faces``: optional (F, 3) int64, a closed, outward-oriented surface whose vertices are
  the tracked points (without it the solid is the convex hull of ``rest_positions``);
* ``scenario``: gravity, ground, initial motion, clamp (:class:`~unipixie.solvers.scenario.Scenario`)
  and the material the model currently believes (homogeneous in the scenario JSON, or a
  per-point field as extra archive keys ``E``, ``nu``, ``density`` of shape (N,)).

A file that breaks the contract is refused with a :class:`~unipixie.core.errors.UserError`
that names the offending key; nothing is written in its place.  Files are written
atomically (a temporary file renamed into place), so a failed save never leaves half a file.

CSV (``t,id,x,y,z``, one observed sample per row, header optional) is read by
:func:`load_csv`; its scenario comes from a side-car JSON file (``name.json`` next to
``name.csv``) or the ``scenario`` argument.
"""

from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from .errors import UserError

MEASUREMENT_FORMAT = "unipixie.measurement/1"
REQUIRED_KEYS = ("positions", "times", "scenario")
OPTIONAL_KEYS = ("rest_positions", "faces", "E", "nu", "density")
CSV_SIDECAR_KEY = "csv_sidecar"
"""Key of the CSV side-car JSON holding what rows cannot carry (point ids, rest positions, faces, per-point material)."""
CSV_COLUMNS = {"t": ("t", "time", "time_s", "t_s", "seconds"), "id": ("id", "point", "point_id", "track", "track_id"),
               "x": ("x", "x_m"), "y": ("y", "y_m"), "z": ("z", "z_m")}
"""The CSV columns and the header names (case-insensitive, any order) each may have."""


def _fail(source: str, msg: str) -> UserError:
    return UserError(f"{source}: {msg}" if source else msg)


# --------------------------------------------------------------------------- material
@dataclass
class MeasuredMaterial:
    """The material the model currently believes for the measured solid.

    E: Pa, nu: -, density: kg/m³ — each a float (homogeneous) or an (N,) array (per tracked point).
    material_class: registry name of the material class (``"jelly"`` by default).
    """

    E: Any
    nu: Any
    density: Any
    material_class: str = "jelly"

    @property
    def homogeneous(self) -> bool:
        return all(np.ndim(v) == 0 for v in (self.E, self.nu, self.density))

    def scaled(self, E_scale: float) -> "MeasuredMaterial":
        """A copy with Young's modulus multiplied by ``E_scale``."""
        E = float(self.E) * E_scale if np.ndim(self.E) == 0 else np.asarray(self.E) * E_scale
        return MeasuredMaterial(E, self.nu, self.density, self.material_class)

    def mean_E(self) -> float:
        return float(np.mean(self.E))

    def mean_density(self) -> float:
        return float(np.mean(self.density))

    def to_spec(self, rest_positions: np.ndarray):
        """The solver-side material: ``HomogeneousMaterial`` or ``PointMaterial`` over the rest positions."""
        from ..solvers.material_sampling import HomogeneousMaterial, PointMaterial
        from ..solvers import materials

        cls_id = materials.get(self.material_class).id
        if self.homogeneous:
            return HomogeneousMaterial(float(self.E), float(self.nu), float(self.density), cls_id)
        n = len(rest_positions)
        arr = {k: np.broadcast_to(np.asarray(getattr(self, k), dtype=np.float64), (n,)).copy()
               for k in ("E", "nu", "density")}
        return PointMaterial(rest_positions, arr["E"], arr["nu"], arr["density"], np.full(n, cls_id, dtype=np.int32))

    def to_dict(self) -> dict:
        """JSON-able summary (per-point fields as mean/min/max)."""
        out: dict[str, Any] = {"material_class": self.material_class}
        for k in ("E", "nu", "density"):
            v = getattr(self, k)
            if np.ndim(v) == 0:
                out[k] = float(v)
            else:
                a = np.asarray(v, dtype=np.float64)
                out[k] = {"mean": float(a.mean()), "min": float(a.min()), "max": float(a.max()), "per_point": True}
        return out


COORDINATE_LIMIT = 1e10
"""Metres: no coordinate of a tracked point may be farther from the origin than this (about 70 times the distance
to the Sun).  Beyond it the value is a sentinel or a unit mistake, and the arithmetic of differences and squares
(noise estimate, errors) loses every digit of the motion or overflows."""


def _check_magnitude(values: np.ndarray, key: str, src: str) -> None:
    with np.errstate(invalid="ignore"):
        biggest = float(np.nanmax(np.abs(values)))
    if biggest > COORDINATE_LIMIT:
        raise _fail(src, f"key '{key}' holds a coordinate of {biggest:.3g} m, beyond {COORDINATE_LIMIT:.0e} m from the "
                         "origin: positions are metres — this is a sentinel value (mark unobserved samples with NaN, "
                         "an empty CSV cell) or a unit mistake")


def _check_material_values(E, nu, density, where: str) -> None:
    E = np.asarray(E, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    density = np.asarray(density, dtype=np.float64)
    if not (np.all(np.isfinite(E)) and np.all(E > 0)):
        raise UserError(f"{where} 'E' must be a positive number of pascals")
    if not (np.all(np.isfinite(nu)) and np.all((nu > -1.0) & (nu < 0.5))):
        raise UserError(f"{where} 'nu' must lie in (-1, 0.5)")
    if not (np.all(np.isfinite(density)) and np.all(density > 0)):
        raise UserError(f"{where} 'density' must be a positive number of kg/m³")


# --------------------------------------------------------------------------- the measurement
@dataclass
class Measurement:
    """Measured motion (see the module docstring for the meaning and units of each field).

    scenario: :class:`~unipixie.solvers.scenario.Scenario`.
    material: :class:`MeasuredMaterial` or ``None`` when the file states none.
    extra_arrays: archive keys outside the contract, kept and written back unchanged.
    source: where it was read from (for messages).
    warnings: what was assumed or repaired while reading.
    """

    positions: np.ndarray
    times: np.ndarray
    scenario: Any = None
    rest_positions: Optional[np.ndarray] = None
    faces: Optional[np.ndarray] = None
    material: Optional[MeasuredMaterial] = None
    extra_arrays: dict = field(default_factory=dict)
    source: str = ""
    warnings: list = field(default_factory=list)

    def __post_init__(self):
        from ..solvers.scenario import Scenario

        src = self.source
        if self.scenario is None:
            self.scenario = Scenario()
        elif isinstance(self.scenario, Mapping):
            self.scenario = _scenario_from_dict(dict(self.scenario), src)[0]
        # positions ---------------------------------------------------------------------
        pos = _float_array(self.positions, "positions", src)
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise _fail(src, f"key 'positions' must have shape (T, N, 3), got {pos.shape}")
        T, N, _ = pos.shape
        if T < 1 or N < 1:
            raise _fail(src, f"key 'positions' is empty (shape {pos.shape})")
        if np.any(np.isinf(pos)):
            raise _fail(src, "key 'positions' contains infinite values (use NaN for unobserved points)")
        pos = pos.copy()
        pos[np.isnan(pos).any(axis=2)] = np.nan  # a sample is observed as a whole or not at all
        if np.isnan(pos).all():
            raise _fail(src, "key 'positions' holds no observed sample (every value is NaN): there is no measured "
                             "motion to read")
        _check_magnitude(pos, "positions", src)
        self.positions = pos
        # times ---------------------------------------------------------------------------
        t = _float_array(self.times, "times", src).reshape(-1) if np.ndim(self.times) <= 1 else None
        if t is None:
            raise _fail(src, f"key 'times' must have shape (T,), got {np.shape(self.times)}")
        if t.shape != (T,):
            raise _fail(src, f"key 'times' has {t.shape[0]} entries but 'positions' has {T} instants")
        if not np.all(np.isfinite(t)):
            raise _fail(src, "key 'times' contains NaN or infinite values")
        if T < 2:
            raise _fail(src, f"key 'times' holds {T} instant: a measurement of motion needs at least two "
                             "(times[0] is the initial state)")
        if not np.all(np.diff(t) > 0):
            i = int(np.argmax(~(np.diff(t) > 0)))
            raise _fail(src, f"key 'times' must be strictly increasing (times[{i}] = {t[i]:g} s, "
                             f"times[{i + 1}] = {t[i + 1]:g} s)")
        self.times = t
        # rest positions ---------------------------------------------------------------
        if self.rest_positions is not None:
            rest = _float_array(self.rest_positions, "rest_positions", src)
            if rest.shape != (N, 3):
                raise _fail(src, f"key 'rest_positions' must have shape ({N}, 3) to match 'positions', got {rest.shape}")
            if not np.all(np.isfinite(rest)):
                raise _fail(src, "key 'rest_positions' contains NaN or infinite values")
            _check_magnitude(rest, "rest_positions", src)
            self.rest_positions = rest
        elif np.isnan(pos[0]).any():
            missing = np.isnan(pos[0, :, 0])
            never = missing & np.all(np.isnan(pos[..., 0]), axis=0)
            if np.any(never) or np.all(missing):
                raise _fail(src, f"key 'rest_positions' is missing and {int(missing.sum())} point(s) are unobserved in "
                                 "positions[0] (some never observed at all), so the rest shape is unknown; add "
                                 "'rest_positions'")
            self.rest_positions = _reconstruct_rest(pos)
            self.warnings.append(f"no 'rest_positions' and {int(missing.sum())} point(s) unobserved in positions[0]: "
                                 "their rest positions were carried back rigidly from their first observation")
        # faces --------------------------------------------------------------------------
        if self.faces is not None:
            self.faces = _check_faces(self.faces, N, src, self.warnings)
        # material ----------------------------------------------------------------------
        if self.material is not None:
            m = self.material
            for k in ("E", "nu", "density"):
                v = getattr(m, k)
                if np.ndim(v) not in (0,) and np.shape(v) != (N,):
                    raise _fail(src, f"key '{k}' must have one value per tracked point ({N},), got {np.shape(v)}")
            _check_material_values(m.E, m.nu, m.density, f"{src}: material" if src else "material")
            from ..solvers import materials

            materials.get(m.material_class)

    # ------------------------------------------------------------------ properties
    @property
    def frame_count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def point_count(self) -> int:
        return int(self.positions.shape[1])

    @property
    def rest(self) -> np.ndarray:
        """(N, 3) metres: ``rest_positions`` or ``positions[0]``."""
        return self.rest_positions if self.rest_positions is not None else self.positions[0]

    @property
    def observed(self) -> np.ndarray:
        """(T, N) bool, True where the point was observed."""
        return ~np.isnan(self.positions[..., 0])

    @property
    def observed_count(self) -> int:
        return int(self.observed.sum())

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def require_material(self) -> MeasuredMaterial:
        if self.material is None:
            raise _fail(self.source, "the measurement states no material: add scenario key 'material' "
                                     "{\"E\": Pa, \"nu\": -, \"density\": kg/m³} (or per-point keys 'E', 'nu', "
                                     "'density'), or give --E/--nu/--density")
        return self.material

    def summary(self) -> str:
        occl = 1.0 - self.observed_count / max(self.positions.shape[0] * self.positions.shape[1], 1)
        return (f"{self.point_count} points × {self.frame_count} instants over {self.duration:.3g} s, "
                f"{100 * occl:.1f} % occluded" + (f", {len(self.faces)} faces" if self.faces is not None else ""))

    # ------------------------------------------------------------------ geometry
    def body(self):
        """The solid to simulate (:class:`~unipixie.solvers.body.Body`); its tracked points are the rest positions.

        With ``faces`` the solid is their inside; without, the convex hull of ``rest_positions``.
        """
        import trimesh

        from ..solvers.body import Body

        rest = np.asarray(self.rest, dtype=np.float64)
        if self.faces is not None:
            mesh = trimesh.Trimesh(vertices=rest, faces=self.faces, process=False)
            body = Body.from_mesh(mesh, tracked_points=rest)
        else:
            if len(rest) < 4:
                raise _fail(self.source, "without 'faces' the solid is the convex hull of 'rest_positions', "
                                         f"which needs at least 4 points (got {len(rest)})")
            try:
                hull = trimesh.convex.convex_hull(rest)
            except Exception as exc:  # qhull errors for flat/degenerate point sets
                raise _fail(self.source, f"the convex hull of 'rest_positions' is degenerate ({exc}); "
                                         "give 'faces'") from None
            if hull.volume <= 1e-12:
                raise _fail(self.source, "the convex hull of 'rest_positions' has no volume (the points are flat); "
                                         "give 'faces'")
            body = Body.from_mesh(hull, tracked_points=rest)
            body.warnings.append("no faces: the solid is the convex hull of the rest positions")
        return body

    # ------------------------------------------------------------------ (de)serialisation
    def scenario_dict(self) -> dict:
        d = self.scenario.to_dict()
        if self.material is not None and self.material.homogeneous:
            d["material"] = {"E": float(self.material.E), "nu": float(self.material.nu),
                             "density": float(self.material.density)}
            if self.material.material_class != "jelly":
                d["material"]["class"] = self.material.material_class
        elif self.material is not None:
            d["material"] = {k: float(np.asarray(getattr(self.material, k)).mean()) for k in ("E", "nu", "density")}
            d["material"]["per_point"] = True
            if self.material.material_class != "jelly":
                d["material"]["class"] = self.material.material_class
        return d

    def save(self, path) -> Path:
        """Write the ``.npz`` (compressed) atomically and verified (:mod:`unipixie.core.atomic_io`); returns the path."""
        path = Path(path)
        arrays: dict[str, Any] = dict(self.extra_arrays)
        arrays["positions"] = self.positions
        arrays["times"] = self.times
        arrays["scenario"] = np.array(json.dumps(self.scenario_dict()))
        if self.rest_positions is not None:
            arrays["rest_positions"] = self.rest_positions
        if self.faces is not None:
            arrays["faces"] = self.faces
        if self.material is not None and not self.material.homogeneous:
            n = self.point_count
            for k in ("E", "nu", "density"):
                arrays[k] = np.broadcast_to(np.asarray(getattr(self.material, k), dtype=np.float64), (n,)).copy()
        _atomic_savez(path, arrays)
        return path

    def save_csv(self, path) -> tuple[Path, list[str]]:
        """Write ``t,id,x,y,z`` rows (observed samples only) and a side-car ``.json`` beside it.

        The side-car holds the scenario and, under key ``csv_sidecar``, what rows cannot carry: every
        point id (also those never observed), the rest positions, the faces and a per-point material, so
        that :func:`load_csv` gives back the same measurement (coordinates to 9 significant digits).
        Returns ``(path, dropped)``: ``dropped`` names what the pair of files does not hold (extra archive
        keys such as ``synth_truth``), for the caller to say.  Both files are written atomically.
        """
        from .atomic_io import write_json, write_text

        path = Path(path)
        obs = self.observed
        ti, pi = np.nonzero(obs)
        ids = self._point_ids()
        lines = ["t,id,x,y,z\n"]
        pos = self.positions
        times = self.times
        lines += [f"{times[t]:.17g},{ids[p]},{pos[t, p, 0]:.17g},{pos[t, p, 1]:.17g},{pos[t, p, 2]:.17g}\n"
                  for t, p in zip(ti.tolist(), pi.tolist())]
        side = self.scenario_dict()
        extra: dict[str, Any] = {"point_ids": list(ids)}
        if self.rest_positions is not None:
            extra["rest_positions"] = np.asarray(self.rest_positions, dtype=np.float64).tolist()
        if self.faces is not None:
            extra["faces"] = np.asarray(self.faces, dtype=np.int64).tolist()
        if self.material is not None and not self.material.homogeneous:
            n = self.point_count
            for k in ("E", "nu", "density"):
                extra[k] = np.broadcast_to(np.asarray(getattr(self.material, k), dtype=np.float64), (n,)).tolist()
        side[CSV_SIDECAR_KEY] = extra
        dropped = sorted(k for k in self.extra_arrays if k != "point_ids")
        side_path = path.with_suffix(".json")
        write_text(path, "".join(lines))
        write_json(side_path, side)
        return path, dropped

    def _point_ids(self) -> list[str]:
        """The points' ids as text (the CSV's ``id`` column): the ids read from a CSV, else 0..N-1."""
        ids = self.extra_arrays.get("point_ids")
        if ids is not None and np.asarray(ids).shape == (self.point_count,):
            out = [str(x) for x in np.asarray(ids).tolist()]
            if len(set(out)) == len(out) and all(out) and not any("," in x or "\n" in x for x in out):
                return out
        return [str(i) for i in range(self.point_count)]

    def subset(self, frames=None, points=None) -> "Measurement":
        """A measurement restricted to some instants and/or points (faces dropped if points change)."""
        fr = slice(None) if frames is None else frames
        pt = slice(None) if points is None else np.asarray(points)
        mat = self.material
        if mat is not None and not mat.homogeneous and points is not None:
            mat = MeasuredMaterial(*(np.broadcast_to(np.asarray(getattr(mat, k)), (self.point_count,))[pt]
                                     for k in ("E", "nu", "density")), mat.material_class)
        return Measurement(self.positions[fr][:, pt], self.times[fr], self.scenario,
                           None if self.rest_positions is None and frames is None else self.rest[pt],
                           self.faces if points is None else None, mat, source=self.source)


# --------------------------------------------------------------------------- helpers
def _float_array(value, key: str, src: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise _fail(src, f"key '{key}' must hold numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def _rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t with R a + t ≈ b (Kabsch; translation only for < 3 points)."""
    ca, cb = a.mean(0), b.mean(0)
    if len(a) < 3:
        return np.eye(3), cb - ca
    H = (a - ca).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def _reconstruct_rest(pos: np.ndarray) -> np.ndarray:
    """Rest positions = positions[0], with points unobserved there carried back from their first
    observation by the rigid motion of the points observed at both instants."""
    rest = pos[0].copy()
    obs = ~np.isnan(pos[..., 0])
    for i in np.nonzero(~obs[0])[0]:
        f = int(np.argmax(obs[:, i]))
        both = obs[0] & obs[f]
        if not np.any(both):
            rest[i] = pos[f, i]
            continue
        R, t = _rigid_fit(pos[f, both], pos[0, both])  # maps instant f back onto instant 0
        rest[i] = R @ pos[f, i] + t
    return rest


def _check_faces(faces, n_points: int, src: str, warnings: list) -> np.ndarray:
    arr = np.asarray(faces)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind == "f" and arr.size and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            arr = arr.astype(np.int64)
        else:
            raise _fail(src, f"key 'faces' must hold integer vertex indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise _fail(src, f"key 'faces' must have shape (F, 3) with F > 0, got {arr.shape}")
    if arr.min() < 0 or arr.max() >= n_points:
        raise _fail(src, f"key 'faces' refers to vertex {int(arr.max()) if arr.max() >= n_points else int(arr.min())}, "
                         f"but there are {n_points} tracked points (indices 0..{n_points - 1})")
    if np.any((arr[:, 0] == arr[:, 1]) | (arr[:, 1] == arr[:, 2]) | (arr[:, 0] == arr[:, 2])):
        raise _fail(src, "key 'faces' has triangles that repeat a vertex")
    # closed: every undirected edge used by exactly two faces, once in each direction (consistent orientation)
    directed = np.concatenate([arr[:, [0, 1]], arr[:, [1, 2]], arr[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if np.any(counts != 2):
        bad = int(np.sum(counts != 2))
        raise _fail(src, f"key 'faces' is not a closed surface ({bad} edge(s) not shared by exactly two triangles)")
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    if np.any(dcounts != 1):
        raise _fail(src, "key 'faces' is not consistently oriented (an edge runs the same way in two triangles)")
    return arr


def _scenario_from_dict(d: dict, src: str):
    """(Scenario, MeasuredMaterial | None) from the scenario JSON dict; errors name the key."""
    from ..solvers.scenario import Scenario

    try:
        scenario = Scenario.from_dict(d)
    except UserError as exc:
        raise _fail(src, f"key 'scenario': {exc}") from None
    material = None
    mat = d.get("material")
    if mat is not None:
        if not isinstance(mat, Mapping):
            raise _fail(src, f"scenario key 'material' must be {{\"E\": Pa, \"nu\": -, \"density\": kg/m³}}, got {mat!r}")
        missing = [k for k in ("E", "nu", "density") if k not in mat]
        if missing:
            raise _fail(src, f"scenario key 'material' lacks {', '.join(repr(k) for k in missing)}")
        from ..solvers.scenario import require_json_numbers

        for k in ("E", "nu", "density"):
            try:
                require_json_numbers(mat[k], f"scenario key 'material' entry '{k}'")
            except UserError as exc:
                raise _fail(src, str(exc)) from None
        try:
            E, nu, rho = (float(mat[k]) for k in ("E", "nu", "density"))
        except (TypeError, ValueError):
            raise _fail(src, f"scenario key 'material' must hold numbers, got {mat!r}") from None
        _check_material_values(E, nu, rho, f"{src}: scenario key 'material'" if src else "scenario key 'material'")
        cls = str(mat.get("class", mat.get("material", "jelly")))
        from ..solvers import materials

        try:
            materials.get(cls)
        except UserError as exc:
            raise _fail(src, f"scenario key 'material': {exc}") from None
        material = MeasuredMaterial(E, nu, rho, cls)
    return scenario, material


MATERIAL_KEYS = ("E", "nu", "density", "class", "material")
"""The keys scenario key ``material`` may hold (``class`` / ``material``: the material class's name)."""


def scenario_key_warnings(d: dict) -> list[str]:
    """Warnings for scenario keys that look like misspellings of the format's own keys.

    The format keeps unknown keys and ignores them (``shared/specs/measurement-format.md`` §1), so a typo such
    as ``initial_velocty`` would silently leave the solid at rest; a key within a close spelling of a known one
    (``difflib``, ratio ≥ 0.8) is named with the key it probably meant.  Keys far from every known one (the
    user's own annotations) pass without a word.
    """
    import difflib

    from ..solvers.scenario import SCENARIO_KEYS

    out = []
    known_top = tuple(SCENARIO_KEYS) + (CSV_SIDECAR_KEY,)
    nested = [("", d, known_top)]
    if isinstance(d.get("material"), Mapping):
        nested.append(("material.", d["material"], MATERIAL_KEYS))
    for prefix, mapping, known in nested:
        for key in mapping:
            if key in known or not isinstance(key, str):
                continue
            close = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
            if close:
                out.append(f"scenario key '{prefix}{key}' is not part of the format and is ignored — did you mean "
                           f"'{prefix}{close[0]}'?")
    return out


def _atomic_savez(path: Path, arrays: dict) -> None:
    from .atomic_io import save_npz

    path = Path(path)
    if path.suffix != ".npz":
        raise UserError(f"{path}: a measurement file must end in .npz")
    save_npz(path, **arrays)


# --------------------------------------------------------------------------- loading
def load_npz(path) -> Measurement:
    """Read and validate a ``unipixie.measurement/1`` archive; a :class:`UserError` names any broken key."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise UserError(f"{src}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise UserError(f"{src}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    for key in REQUIRED_KEYS:
        if key not in data:
            raise UserError(f"{src}: key '{key}' is missing (a measurement needs {', '.join(REQUIRED_KEYS)})")
    sc = data["scenario"]
    if sc.dtype.kind not in "US" or sc.ndim != 0:
        raise UserError(f"{src}: key 'scenario' must be a 0-d string array holding JSON, got dtype {sc.dtype} "
                        f"shape {sc.shape}")
    try:
        sdict = json.loads(str(sc))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise UserError(f"{src}: key 'scenario' is not valid JSON ({exc})") from None
    if not isinstance(sdict, dict):
        raise UserError(f"{src}: key 'scenario' must be a JSON object")
    scenario, material = _scenario_from_dict(sdict, src)
    positions = data["positions"]
    n = positions.shape[1] if positions.ndim == 3 else None
    per_point = {k: data[k] for k in ("E", "nu", "density") if k in data}
    if per_point:
        for k, v in per_point.items():
            if v.dtype.kind not in "fiu" or (n is not None and v.shape != (n,)):
                raise UserError(f"{src}: key '{k}' must be a float array of shape ({n},) (one value per tracked point), "
                                f"got dtype {v.dtype} shape {v.shape}")
        if material is None and len(per_point) < 3:
            lacking = [k for k in ("E", "nu", "density") if k not in per_point]
            raise UserError(f"{src}: per-point material keys given but {', '.join(repr(k) for k in lacking)} missing "
                            "and the scenario states no 'material' to fill them")
        base = material or MeasuredMaterial(0, 0, 0)
        material = MeasuredMaterial(*(per_point[k].astype(np.float64) if k in per_point else getattr(base, k)
                                      for k in ("E", "nu", "density")), base.material_class)
    extras = {k: v for k, v in data.items() if k not in REQUIRED_KEYS + OPTIONAL_KEYS}
    m = Measurement(positions=positions, times=data["times"], scenario=scenario,
                    rest_positions=data.get("rest_positions"), faces=data.get("faces"), material=material,
                    extra_arrays=extras, source=src)
    m.warnings.extend(scenario_key_warnings(sdict))
    return m


def _csv_columns(row: list, src: str, lineno: int) -> Optional[dict]:
    """``{"t": index, "id": ..., "x": ..., "y": ..., "z": ...}`` from a header row (names as
    :data:`CSV_COLUMNS`, case-insensitive, any order), or ``None`` when ``row`` is data (its first
    cell a number)."""
    cells = [c.strip().lower() for c in row]
    try:
        float(cells[0])
        return None  # data, no header
    except ValueError:
        pass
    cols: dict = {}
    for i, c in enumerate(cells):
        for name, aliases in CSV_COLUMNS.items():
            if c in aliases:
                if name in cols:
                    raise UserError(f"{src}: line {lineno}: the header names column '{name}' twice "
                                    f"({row[cols[name]]!r} and {row[i]!r})")
                cols[name] = i
    missing = [n for n in CSV_COLUMNS if n not in cols]
    if missing:
        raise UserError(f"{src}: line {lineno}: the header {','.join(row)!r} lacks column(s) {', '.join(missing)}; "
                        "a measurement CSV has columns t (s), id, x, y, z (m) — named in the header in any order "
                        "(case-insensitive), or in that order without a header")
    return cols


def _csv_id(text: str, src: str, lineno: int) -> str:
    """A point id as written: an integer (``"7"``, also ``"7.0"`` → ``"7"``) or a name; a number that is
    not whole (``"1.5"``) is refused rather than read as a new point."""
    t = text.strip()
    if not t:
        raise UserError(f"{src}: line {lineno}: column 'id' is empty")
    try:
        return str(int(t))
    except ValueError:
        pass
    try:
        v = float(t)
    except ValueError:
        return t  # a name
    if math.isfinite(v) and v == round(v):
        return str(int(v))
    raise UserError(f"{src}: line {lineno}: point id {t!r} is not a whole number; ids are integers (or names), "
                    "one per tracked point")


def load_csv(path, scenario=None, rest_positions=None, faces=None) -> Measurement:
    """Read ``t,id,x,y,z`` rows (seconds, point id, metres) into a measurement.

    The columns are found by the header's names (:data:`CSV_COLUMNS`: ``t``/``time``, ``id``/``point``,
    ``x``, ``y``, ``z``; case-insensitive, any order, other columns ignored with a warning); a file
    without a header is read in the order ``t,id,x,y,z``.  Missing (t, id) pairs and empty/``nan``
    coordinates become NaN (unobserved).  Point ids are whole numbers or names (``"1.5"`` is refused);
    they are sorted (numerically when all are integers); instants are the sorted distinct ``t``.
    scenario: dict / JSON path / ``None`` (then ``<name>.json`` beside the CSV if it exists, else the
    default scenario with no material).  A side-car written by :meth:`Measurement.save_csv` also gives
    back the point ids never observed, the rest positions, the faces and a per-point material.
    """
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise UserError(f"{src}: file not found")
    ts: list[float] = []
    ids: list[str] = []
    xyz: list[tuple[float, float, float]] = []
    cols: Optional[dict] = None
    header_seen = False
    warnings: list[str] = []
    try:
        f = open(path, newline="", encoding="utf-8-sig")  # -sig: a byte-order mark (Excel's "CSV UTF-8") is not a name
    except OSError as exc:
        raise UserError(f"{src}: cannot read it ({exc.strerror or exc})") from None
    try:
        with f:
            reader = csv.reader(f)
            for lineno, row in enumerate(reader, start=1):
                if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if not header_seen:
                    header_seen = True
                    cols = _csv_columns(row, src, lineno)
                    named = cols is not None
                    width = len(row)
                    if cols is not None:
                        ignored = [row[i] for i in range(len(row)) if i not in cols.values()]
                        if ignored:
                            warnings.append(f"CSV columns {', '.join(repr(c) for c in ignored)} are ignored")
                        continue
                    if len(row) != 5:
                        raise UserError(f"{src}: line {lineno}: expected 5 columns t,id,x,y,z (or a header naming "
                                        f"them), got {len(row)}")
                    cols = {"t": 0, "id": 1, "x": 2, "y": 3, "z": 4}
                    warnings.append("the CSV has no header: its columns are read in the order t,id,x,y,z (name them "
                                    "in a first line, in any order, to read them by name)")
                if len(row) <= max(cols.values()):
                    raise UserError(f"{src}: line {lineno}: expected {max(cols.values()) + 1} columns, got {len(row)}")
                if len(row) > width and any(c.strip() for c in row[width:]):
                    raise UserError(f"{src}: line {lineno}: {len(row)} cells where the "
                                    f"{'header names' if named else 'rows t,id,x,y,z have'} {width}: the row does "
                                    "not belong to this table (a stray separator or a joined line)")
                try:
                    t = float(row[cols["t"]])
                except ValueError:
                    raise UserError(f"{src}: line {lineno}: column 't' is not a number: {row[cols['t']]!r}") from None
                vals = []
                for name in "xyz":
                    c = row[cols[name]].strip()
                    try:
                        vals.append(float(c) if c else math.nan)
                    except ValueError:
                        raise UserError(f"{src}: line {lineno}: column '{name}' is not a number: {c!r}") from None
                if not math.isfinite(t):
                    raise UserError(f"{src}: line {lineno}: column 't' must be finite")
                ts.append(t)
                ids.append(_csv_id(row[cols["id"]], src, lineno))
                xyz.append(tuple(vals))
    except UnicodeDecodeError:
        raise UserError(f"{src}: not a text CSV file (not UTF-8)") from None
    except csv.Error as exc:
        raise UserError(f"{src}: not a readable CSV file ({exc})") from None
    if not ts:
        raise UserError(f"{src}: no data rows (expected t,id,x,y,z)")
    sdict = None
    if scenario is None:
        side = path.with_suffix(".json")
        if side.is_file():
            scenario = side
    if isinstance(scenario, (str, os.PathLike)):
        sp = Path(scenario)
        from .errors import read_json

        if not sp.is_file():
            raise UserError(f"{sp}: scenario file not found")
        sdict = read_json(sp)
        if not isinstance(sdict, dict):
            raise UserError(f"{sp}: the scenario must be a JSON object")
        src_sc = str(sp)
    elif isinstance(scenario, Mapping):
        sdict, src_sc = dict(scenario), src
    else:
        sdict, src_sc = {"format": MEASUREMENT_FORMAT}, src
        warnings.append(f"no scenario for this CSV (no {path.with_suffix('.json').name} beside it, no --scenario): "
                        "the default is assumed — gravity (0, 0, -9.81) m/s², ground at z = 0 m, starting at rest, no "
                        "clamp, no material stated")
    sidecar = sdict.pop(CSV_SIDECAR_KEY, None) if isinstance(sdict, dict) else None
    if sidecar is not None and not isinstance(sidecar, Mapping):
        raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}' must be a JSON object")
    sidecar = dict(sidecar or {})
    t_arr = np.asarray(ts)
    # distinct instants, merging times equal to within a nanosecond
    order = np.argsort(t_arr, kind="stable")
    uniq: list[float] = []
    for v in t_arr[order]:
        if not uniq or v - uniq[-1] > 1e-9:
            uniq.append(float(v))
    times = np.asarray(uniq)
    t_index = np.clip(np.searchsorted(times, t_arr - 1e-9), 0, len(times) - 1)
    all_ids = set(ids)
    side_ids = sidecar.get("point_ids")
    if side_ids is not None:
        if not isinstance(side_ids, list) or len(set(map(str, side_ids))) != len(side_ids):
            raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}.point_ids' must be a list of distinct ids")
        side_ids = [str(x) for x in side_ids]
        unknown = sorted(all_ids - set(side_ids))
        if unknown:
            raise UserError(f"{src}: point id(s) {', '.join(unknown[:5])} are not in the side-car's point_ids; the "
                            "CSV and its side-car JSON do not belong together")
        keys = side_ids
    else:
        try:
            keys = sorted(all_ids, key=int)
        except ValueError:
            keys = sorted(all_ids)
    p_index_of = {k: i for i, k in enumerate(keys)}
    positions = np.full((len(times), len(keys), 3), np.nan)
    seen = np.zeros((len(times), len(keys)), dtype=bool)
    for t_i, pid, v in zip(t_index, ids, xyz):
        p_i = p_index_of[pid]
        if seen[t_i, p_i]:
            raise UserError(f"{src}: point id {pid!r} appears twice at t = {times[t_i]:g} s")
        seen[t_i, p_i] = True
        positions[t_i, p_i] = v
    from ..solvers.scenario import require_json_numbers

    for key in ("rest_positions", "faces", "E", "nu", "density"):
        if sidecar.get(key) is not None:
            try:
                require_json_numbers(sidecar[key], f"key '{CSV_SIDECAR_KEY}.{key}'")
            except UserError as exc:
                raise UserError(f"{src_sc}: {exc}") from None
    if rest_positions is None and sidecar.get("rest_positions") is not None:
        rest_positions = _float_array(sidecar["rest_positions"], f"{CSV_SIDECAR_KEY}.rest_positions", src_sc)
    if faces is None and sidecar.get("faces") is not None:
        faces = np.asarray(sidecar["faces"])
    sc, material = _scenario_from_dict(sdict, src_sc)
    per_point = {k: sidecar[k] for k in ("E", "nu", "density") if sidecar.get(k) is not None}
    if per_point:
        base = material or MeasuredMaterial(0, 0, 0)
        vals = []
        for k in ("E", "nu", "density"):
            if k in per_point:
                arr = _float_array(per_point[k], f"{CSV_SIDECAR_KEY}.{k}", src_sc)
                if arr.shape != (len(keys),):
                    raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}.{k}' must hold one value per point "
                                    f"({len(keys)}), got shape {arr.shape}")
                vals.append(arr)
            else:
                vals.append(getattr(base, k))
        material = MeasuredMaterial(*vals, base.material_class)
    m = Measurement(positions=positions, times=times, scenario=sc, rest_positions=rest_positions, faces=faces,
                    material=material, source=src)
    m.warnings.extend(warnings + scenario_key_warnings(sdict))
    if keys != [str(i) for i in range(len(keys))]:  # ids 0..N-1 are the positions themselves: nothing to keep
        m.extra_arrays["point_ids"] = np.asarray(keys)
    return m


def load(path, **kwargs) -> Measurement:
    """Load a measurement by extension: ``.npz`` (the spec's format) or ``.csv`` (t,id,x,y,z)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        if kwargs:
            raise UserError(f"{path}: options {sorted(kwargs)} apply to CSV files only")
        return load_npz(path)
    if suffix == ".csv":
        return load_csv(path, **kwargs)
    raise UserError(f"{path}: unknown measurement file type {suffix!r}; use .npz ({MEASUREMENT_FORMAT}) or .csv "
                    "(t,id,x,y,z)")
