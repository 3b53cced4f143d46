"""Procedural objects for the dataset: ten semantic classes made of named, textured parts.

Every object is built with trimesh from closed primitives (solids of
revolution, displaced ellipsoids, rods, boxes, annuli), in metres at a
realistic size, standing on (or lying on) the plane z = 0.  Its **parts**
(``"pot"``, ``"soil"``, ``"trunk"``, ``"leaves"``, ...) are the parts of the
class prior in :mod:`unipixie.core.annotation`; each part is one or more closed
*components* (a crown of leaf blobs, four chair legs).  The solid of the
object is the union of its parts; where parts overlap, the **later part in
the list wins** (a ball's core inside its cover, a trunk entering the crown).

Appearance carries information about the material: every part gets an
*appearance code* u ∈ [0, 1] that sets its colour between the palette's
"soft-looking" and "stiff-looking" colours and its texture's contrast and
frequency, and the same u places the part's stiffness range inside the prior
(:func:`unipixie.core.annotation.sample_annotation`).  Textures are procedural images
(noise, speckle, stripes, wood grain, brushed metal, panels, fur) baked into
one PNG per part and mapped with spherical, cylindrical or box UVs; the object
is exported as ``.glb`` with one named mesh and one PBR material per part, so
Blender renders it as it is.

Everything is a function of ``(seed, index)``: :func:`generate` is
deterministic.

    obj = generate(index=7, seed=0)                   # class by index, everything else seeded
    obj.export_glb("object.glb")
    occ, part_ids = obj.voxel_labels(geometry_world)   # union occupancy and part id per occupied voxel
    points, part_of_point = obj.fill(spacing=0.01)      # solid sample points (MPM particles)

One module per job: the primitives (:mod:`.shapes`), each class's geometry
(:mod:`.geometry`), the palettes and appearance codes (:mod:`.appearance`),
textures and UVs (:mod:`.textures`), the object and its parts with export,
voxels and samples (:mod:`.objects`), and the assembly of object ``index``
(:mod:`.generation`).  This face re-exports the public names; the modules
import each other directly.
"""

from .appearance import PALETTES, Appearance, Look, look_for
from .generation import class_of_index, generate, make_scenario, object_id
from .geometry import GEOMETRY
from .objects import Z_UP_TO_GLTF, Part, ProceduralObject
from .textures import PATTERNS, TEXTURE_SIZE, texture_image
