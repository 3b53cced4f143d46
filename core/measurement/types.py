"""The measurement itself (:class:`Measurement`): measured motion of tracked points and the checks it passes.

Owns the fields of a measurement (positions, times, rest positions, faces, scenario, material), their checks
when one is made (every reader ends here, so a file and a measurement built in code are refused alike), what
is derived from them (observed samples, the solid to simulate, subsets) and the entry points to write one.  It
may use :mod:`unipixie.core.errors`, :mod:`.arrays`, :mod:`.material`, :mod:`.scenario_json`, :mod:`.writing`
and, inside functions, :mod:`unipixie.solvers` and trimesh; never the readers (:mod:`.npz`, :mod:`.csv_reader`,
:mod:`.loading`), which build on it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np

from .arrays import check_faces, check_magnitude, fail, float_array, reconstruct_rest
from .material import MeasuredMaterial, check_material_values
from .scenario_json import scenario_from_dict
from .writing import write_csv, write_npz


@dataclass
class Measurement:
    """Measured motion (see :mod:`unipixie.core.measurement` for the meaning and units of each field).

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
        from ...solvers.scenario import Scenario

        src = self.source
        if self.scenario is None:
            self.scenario = Scenario()
        elif isinstance(self.scenario, Mapping):
            self.scenario = scenario_from_dict(dict(self.scenario), src)[0]
        # positions ---------------------------------------------------------------------
        pos = float_array(self.positions, "positions", src)
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise fail(src, f"key 'positions' must have shape (T, N, 3), got {pos.shape}")
        T, N, _ = pos.shape
        if T < 1 or N < 1:
            raise fail(src, f"key 'positions' is empty (shape {pos.shape})")
        if np.any(np.isinf(pos)):
            raise fail(src, "key 'positions' contains infinite values (use NaN for unobserved points)")
        pos = pos.copy()
        pos[np.isnan(pos).any(axis=2)] = np.nan  # a sample is observed as a whole or not at all
        if np.isnan(pos).all():
            raise fail(src, "key 'positions' holds no observed sample (every value is NaN): there is no measured "
                             "motion to read")
        check_magnitude(pos, "positions", src)
        self.positions = pos
        # times ---------------------------------------------------------------------------
        t = float_array(self.times, "times", src).reshape(-1) if np.ndim(self.times) <= 1 else None
        if t is None:
            raise fail(src, f"key 'times' must have shape (T,), got {np.shape(self.times)}")
        if t.shape != (T,):
            raise fail(src, f"key 'times' has {t.shape[0]} entries but 'positions' has {T} instants")
        if not np.all(np.isfinite(t)):
            raise fail(src, "key 'times' contains NaN or infinite values")
        if T < 2:
            raise fail(src, f"key 'times' holds {T} instant: a measurement of motion needs at least two "
                             "(times[0] is the initial state)")
        if not np.all(np.diff(t) > 0):
            i = int(np.argmax(~(np.diff(t) > 0)))
            raise fail(src, f"key 'times' must be strictly increasing (times[{i}] = {t[i]:g} s, "
                             f"times[{i + 1}] = {t[i + 1]:g} s)")
        self.times = t
        # rest positions ---------------------------------------------------------------
        if self.rest_positions is not None:
            rest = float_array(self.rest_positions, "rest_positions", src)
            if rest.shape != (N, 3):
                raise fail(src, f"key 'rest_positions' must have shape ({N}, 3) to match 'positions', got {rest.shape}")
            if not np.all(np.isfinite(rest)):
                raise fail(src, "key 'rest_positions' contains NaN or infinite values")
            check_magnitude(rest, "rest_positions", src)
            self.rest_positions = rest
        elif np.isnan(pos[0]).any():
            missing = np.isnan(pos[0, :, 0])
            never = missing & np.all(np.isnan(pos[..., 0]), axis=0)
            if np.any(never) or np.all(missing):
                raise fail(src, f"key 'rest_positions' is missing and {int(missing.sum())} point(s) are unobserved in "
                                 "positions[0] (some never observed at all), so the rest shape is unknown; add "
                                 "'rest_positions'")
            self.rest_positions = reconstruct_rest(pos)
            self.warnings.append(f"no 'rest_positions' and {int(missing.sum())} point(s) unobserved in positions[0]: "
                                 "their rest positions were carried back rigidly from their first observation")
        # faces --------------------------------------------------------------------------
        if self.faces is not None:
            self.faces = check_faces(self.faces, N, src, self.warnings)
        # material ----------------------------------------------------------------------
        if self.material is not None:
            m = self.material
            for k in ("E", "nu", "density"):
                v = getattr(m, k)
                if np.ndim(v) not in (0,) and np.shape(v) != (N,):
                    raise fail(src, f"key '{k}' must have one value per tracked point ({N},), got {np.shape(v)}")
            check_material_values(m.E, m.nu, m.density, f"{src}: material" if src else "material")
            from ...solvers import materials

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
            raise fail(self.source, "the measurement states no material: add scenario key 'material' "
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

        from ...solvers.body import Body

        rest = np.asarray(self.rest, dtype=np.float64)
        if self.faces is not None:
            mesh = trimesh.Trimesh(vertices=rest, faces=self.faces, process=False)
            body = Body.from_mesh(mesh, tracked_points=rest)
        else:
            if len(rest) < 4:
                raise fail(self.source, "without 'faces' the solid is the convex hull of 'rest_positions', "
                                         f"which needs at least 4 points (got {len(rest)})")
            try:
                hull = trimesh.convex.convex_hull(rest)
            except Exception as exc:  # qhull errors for flat/degenerate point sets
                raise fail(self.source, f"the convex hull of 'rest_positions' is degenerate ({exc}); "
                                         "give 'faces'") from None
            if hull.volume <= 1e-12:
                raise fail(self.source, "the convex hull of 'rest_positions' has no volume (the points are flat); "
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
        return write_npz(self, path)

    def save_csv(self, path) -> tuple[Path, list[str]]:
        """Write ``t,id,x,y,z`` rows (observed samples only) and a side-car ``.json`` beside it.

        The side-car holds the scenario and, under key ``csv_sidecar``, what rows cannot carry: every
        point id (also those never observed), the rest positions, the faces and a per-point material, so
        that :func:`~.csv_reader.load_csv` gives back the same measurement (coordinates to 9 significant digits).
        Returns ``(path, dropped)``: ``dropped`` names what the pair of files does not hold (extra archive
        keys such as ``synth_truth``), for the caller to say.  Both files are written atomically.
        """
        return write_csv(self, path)

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
