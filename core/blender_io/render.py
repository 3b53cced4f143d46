"""Multi-view rendering of an object normalised into the unit cube (RGB + depth + cameras → ``Views``).

The object (one or several Blender objects with geometry: the *subject*) is
copied — modifiers applied, materials and textures as they are — into a
temporary scene, moved and scaled into the normalised cube
(:class:`~unipixie.core.normalise.Normalisation`: bounding-box centre at the
origin, largest extent 1), and rendered from ``view_count`` cameras on a
Fibonacci sphere looking at the origin.  The user's scenes, objects,
selection and render settings are never changed: everything is created in
the temporary scene and removed afterwards (also on errors and on Esc).

Lighting is even and fixed in the object's frame, so a surface point looks the
same from every view: a uniform grey world (ambient light from all sides) and
two sun lamps (from above-front and, weaker, from below-behind).  Cycles
renders on the CPU by default (``device="auto"`` uses a GPU the user's Cycles
preferences, or a CUDA/OptiX/HIP/oneAPI/Metal backend, provides), Workbench
is the fast option (studio lighting, texture colours).

With ``passes`` (Cycles) it also writes the surface-appearance passes of :mod:`.render_passes`.
Per view the compositor writes the display-referred colour (view transform
*Standard*, sRGB, 8-bit PNG with alpha, composited over ``background`` here)
and the Z pass (float EXR: distance along the camera's viewing axis, in
normalised units; background → ``inf``).  Cameras: perspective, square
images, field of view ``fov_degrees``, distance chosen so the subject's
bounding sphere (about the origin) fills the view.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Generator

import bpy
import numpy as np

from ..errors import UserError
from ..jobs import run_job
from ..lift import camera_rig, look_at_origin
from ..normalise import Normalisation
from ..render_defaults import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT
from ..types import Views
from . import render_passes
from .compositor import file_output_node
from .scene_import import geometry_objects, quiet_blender_output, remove_new_ids, snapshot_ids

ENGINES = ("cycles", "workbench")
RENDER_VERSION = 1
"""Bumped when the way views are rendered changes (part of cache keys)."""


@dataclass
class RenderSettings:
    """How to render the views.

    view_count: number of cameras (Fibonacci sphere).  resolution: square image side in pixels.
    engine: ``"cycles"`` or ``"workbench"``.  samples: Cycles samples per pixel (adaptive sampling on,
    denoising off).  device: ``"cpu"``, ``"gpu"`` or ``"auto"`` for Cycles.  fov_degrees: camera field
    of view.  background: RGB in [0, 1] the images are composited over (display sRGB).
    passes: also render the surface-appearance passes (:mod:`.render_passes`: base colour, roughness,
    metallic, normal) into :attr:`Views.passes` (Cycles only; what the appearance extractor reads).
    """

    view_count: int = DEFAULT_VIEW_COUNT
    resolution: int = DEFAULT_RESOLUTION
    engine: str = "cycles"
    samples: int = DEFAULT_SAMPLES
    device: str = "cpu"
    fov_degrees: float = 40.0
    background: tuple = (1.0, 1.0, 1.0)
    passes: bool = False

    def __post_init__(self):
        self.engine = str(self.engine).lower()
        if self.engine not in ENGINES:
            raise UserError(f"render engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")
        if int(self.view_count) < 1:
            raise UserError(f"view count must be at least 1, got {self.view_count}")
        if not 16 <= int(self.resolution) <= 4096:
            raise UserError(f"render resolution must be between 16 and 4096 pixels, got {self.resolution}")
        if int(self.samples) < 1:
            raise UserError(f"samples must be at least 1, got {self.samples}")
        if not 5.0 <= float(self.fov_degrees) <= 120.0:
            raise UserError(f"field of view must be between 5 and 120 degrees, got {self.fov_degrees}")
        self.view_count, self.resolution, self.samples = int(self.view_count), int(self.resolution), int(self.samples)
        self.device = str(self.device).lower()
        if self.device.startswith("cuda"):
            self.device = "gpu"
        if self.device not in ("cpu", "gpu", "auto"):
            raise UserError(f"render device must be cpu, gpu (cuda) or auto, got {self.device!r}")
        self.background = tuple(float(c) for c in self.background)
        self.passes = bool(self.passes)
        if self.passes and self.engine != "cycles":
            from ..extractors import PASSES_NEED_CYCLES

            raise UserError(PASSES_NEED_CYCLES)

    def key(self) -> dict:
        """What determines the images (for cache keys); the Cycles device does not."""
        d = asdict(self)
        d.pop("device")
        if not self.passes:
            d.pop("passes")             # colour-only renders keep their cache keys
        d["version"] = RENDER_VERSION
        if self.engine == "workbench":
            d.pop("samples")
        return d


# --------------------------------------------------------------------------- the subject's geometry
def _as_list(objects) -> list:
    if isinstance(objects, bpy.types.Object):
        return [objects]
    return list(objects)


def _depsgraph_of(obj):
    """The evaluated dependency graph of a scene that holds ``obj`` (the current view layer when it shows
    it), so modifiers and parents are applied also to objects living only in a temporary scene."""
    context = bpy.context
    if context.view_layer is not None and context.view_layer.objects.get(obj.name) == obj:
        return context.evaluated_depsgraph_get()
    for scene in obj.users_scene:
        # the scene's own view layer, evaluated in place: no context override (see .context_safety)
        view_layer = scene.view_layers[0]
        view_layer.update()          # creates and evaluates the view layer's depsgraph
        return view_layer.depsgraph
    raise UserError(f"object {obj.name!r} is in no scene; link it to a scene to render it")


@contextlib.contextmanager
def evaluated_meshes(objects):
    """Yield [(object, mesh copy with modifiers applied and effective materials, (4, 4) world matrix)].

    The mesh copies are temporary data-blocks, removed on exit.
    """
    objs = geometry_objects(_as_list(objects))
    out = []
    try:
        for obj in objs:
            evaluated = obj.evaluated_get(_depsgraph_of(obj))
            mesh = bpy.data.meshes.new_from_object(evaluated, preserve_all_data_layers=True,
                                                   depsgraph=_depsgraph_of(obj))
            for i, slot in enumerate(obj.material_slots):
                if i < len(mesh.materials):
                    mesh.materials[i] = slot.material          # object-linked materials included
            out.append((obj, mesh, np.array(evaluated.matrix_world, dtype=np.float64)))
        yield out
    finally:
        for _, mesh, _ in out:
            try:
                bpy.data.meshes.remove(mesh)
            except ReferenceError:         # already removed with the temporary scene
                pass


def _triangles(mesh, matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mesh.calc_loop_triangles()
    verts = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", verts)
    verts = verts.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    tris = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return verts, tris.reshape(-1, 3)


def subject_mesh(objects) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of the subject: ((N, 3) float64 vertices in metres, (F, 3) int64 faces).

    Raises :class:`UserError` when the subject has no faces.
    """
    with evaluated_meshes(objects) as meshes:
        return _collect_triangles(meshes)


def _collect_triangles(meshes) -> tuple[np.ndarray, np.ndarray]:
    all_v, all_f, offset = [], [], 0
    for _, mesh, matrix in meshes:
        v, f = _triangles(mesh, matrix)
        all_v.append(v)
        all_f.append(f + offset)
        offset += len(v)
    verts = np.concatenate(all_v) if all_v else np.zeros((0, 3))
    faces = np.concatenate(all_f) if all_f else np.zeros((0, 3), dtype=np.int64)
    if len(faces) == 0:
        names = ", ".join(o.name for o, _, _ in meshes)
        raise UserError(f"{names}: the object has no faces (only vertices or edges); UniPixie needs a surface "
                        "to render and voxelise")
    if not np.all(np.isfinite(verts)):
        raise UserError("the object has NaN or infinite vertex positions")
    return verts, faces


# --------------------------------------------------------------------------- fingerprint (cache key)
def _hash_array(h, arr) -> None:
    a = np.ascontiguousarray(arr)
    h.update(str(a.dtype).encode() + str(a.shape).encode())
    h.update(a.tobytes())


def _image_fingerprint(img, h) -> None:
    h.update(f"image:{img.name}:{img.source}:{tuple(img.size)}:{img.colorspace_settings.name}:{img.alpha_mode}".encode())
    if img.is_dirty:                   # painted or edited in this session: what is in memory counts
        px = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(px)
        _hash_array(h, px)
        return
    if img.source == "GENERATED":
        h.update(f"{img.generated_type}:{tuple(img.generated_color)}:{img.generated_width}x{img.generated_height}".encode())
        return
    if img.packed_file is not None:
        h.update(bytes(img.packed_file.data))
        return
    path = Path(bpy.path.abspath(img.filepath)) if img.filepath else None
    if path is not None and path.is_file():
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        return
    if img.has_data:                   # in memory only
        px = np.empty(len(img.pixels), dtype=np.float32)
        img.pixels.foreach_get(px)
        _hash_array(h, px)


_SKIP_PROPS = {"location", "location_absolute", "width", "height", "dimensions", "select", "show_options",
               "show_preview", "show_texture", "hide", "color", "use_custom_color", "label", "parent", "rna_type",
               "bl_width_default", "bl_width_min", "bl_width_max", "bl_height_default", "bl_height_min",
               "bl_height_max", "internal_links", "inputs", "outputs", "warning_propagation", "color_tag"}


def _value(v):
    if isinstance(v, (int, float, str, bool)) or v is None:
        return v
    try:
        return [(_value(x)) for x in v]
    except TypeError:
        return str(v)


def _node_tree_fingerprint(tree, h, seen: set) -> None:
    if tree is None or tree.name_full in seen:
        return
    seen.add(tree.name_full)
    h.update(f"tree:{tree.bl_idname}".encode())
    for node in sorted(tree.nodes, key=lambda n: n.name):
        desc = {"type": node.bl_idname, "name": node.name, "mute": node.mute}
        for prop in node.bl_rna.properties:
            ident = prop.identifier
            if ident in _SKIP_PROPS or ident.startswith("bl_"):
                continue
            val = getattr(node, ident, None)
            if prop.type == "POINTER":
                if isinstance(val, bpy.types.Image):
                    _image_fingerprint(val, h)
                elif isinstance(val, bpy.types.NodeTree):
                    _node_tree_fingerprint(val, h, seen)
                elif isinstance(val, bpy.types.ID):
                    desc[ident] = val.name_full
                continue
            if prop.type in ("BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"):
                desc[ident] = _value(val)
        desc["inputs"] = [(s.identifier, _value(getattr(s, "default_value", None))) for s in node.inputs]
        h.update(json.dumps(desc, sort_keys=True, default=str).encode())
    links = sorted((l.from_node.name, l.from_socket.identifier, l.to_node.name, l.to_socket.identifier)
                   for l in tree.links)
    h.update(json.dumps(links).encode())


def _mesh_attributes_fingerprint(mesh, h) -> None:
    for uv in mesh.uv_layers:
        arr = np.empty(len(uv.uv) * 2, dtype=np.float32)
        uv.uv.foreach_get("vector", arr)
        h.update(f"uv:{uv.name}".encode())
        _hash_array(h, arr)
    for attr in mesh.color_attributes:
        arr = np.empty(len(attr.data) * 4, dtype=np.float32)
        attr.data.foreach_get("color", arr)
        h.update(f"color:{attr.name}:{attr.domain}".encode())
        _hash_array(h, arr)
    mat_idx = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("material_index", mat_idx)
    _hash_array(h, mat_idx)


@dataclass
class SubjectInfo:
    """The subject as the pipeline needs it: world-space triangles and a fingerprint for cache keys.

    vertices: (N, 3) float64 metres.  faces: (F, 3) int64.  fingerprint: hex digest of what the renders
    depend on.  names: the objects' names.
    """

    vertices: np.ndarray
    faces: np.ndarray
    fingerprint: str
    names: list


def describe_subject(objects, placement_invariant: bool = False) -> SubjectInfo:
    """World-space triangles and the fingerprint of geometry, UVs, colour attributes, material node trees
    (values and links) and the pixels / files of their images.

    placement_invariant: hash the vertices in the normalised cube (:mod:`..normalise`, rounded to 1e-6 of
    the subject's size) instead of world space, so moving or uniformly scaling the subject keeps its
    fingerprint (what the object pipeline uses to tell when features are stale)."""
    h = hashlib.sha256()
    seen: set = set()
    with evaluated_meshes(objects) as meshes:
        verts, faces = _collect_triangles(meshes)
        if placement_invariant:
            from ..normalise import Normalisation

            h.update(b"normalised")
            _hash_array(h, np.rint(Normalisation.from_points(verts).to_normalised(verts) * 1e6).astype(np.int32))
        else:
            _hash_array(h, verts.astype(np.float32))
        _hash_array(h, faces)
        for _, mesh, _ in meshes:
            _mesh_attributes_fingerprint(mesh, h)
            for mat in mesh.materials:
                if mat is None:
                    h.update(b"material:none")
                    continue
                h.update(f"material:{mat.name_full}:{tuple(mat.diffuse_color)}:{mat.roughness}:{mat.metallic}".encode())
                _node_tree_fingerprint(mat.node_tree, h, seen)
        names = [o.name for o, _, _ in meshes]
    return SubjectInfo(vertices=verts, faces=faces, fingerprint=h.hexdigest()[:32], names=names)


def subject_fingerprint(objects) -> str:
    """The fingerprint of :func:`describe_subject`."""
    return describe_subject(objects).fingerprint


# --------------------------------------------------------------------------- the temporary scene
def _setup_world(scene) -> None:
    world = bpy.data.worlds.new("UniPixie even light")
    if world.node_tree is None:                    # Blender < 5 creates worlds without nodes
        world.use_nodes = True
    bg = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    bg.inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world
    for name, direction, strength in (("key", (0.4, -0.6, 1.0), 2.0), ("fill", (-0.4, 0.6, -1.0), 0.7)):
        light = bpy.data.lights.new(f"UniPixie {name}", type="SUN")
        light.energy = strength
        obj = bpy.data.objects.new(f"UniPixie {name}", light)
        obj.matrix_world = _matrix(look_at_origin(np.asarray(direction, dtype=np.float64)))
        scene.collection.objects.link(obj)


def _matrix(m: np.ndarray):
    import mathutils

    return mathutils.Matrix([list(row) for row in np.asarray(m, dtype=np.float64)])


@contextlib.contextmanager
def _cycles_device(requested: str):
    """Yield "GPU" or "CPU" for ``scene.cycles.device``; restores the user's Cycles preferences on exit."""
    if requested == "cpu":
        yield "CPU"
        return
    addon = bpy.context.preferences.addons.get("cycles")
    prefs = addon.preferences if addon is not None else None
    if prefs is None:
        if requested == "gpu":
            raise UserError("GPU rendering requested but Cycles' preferences are not available; use --render-device cpu")
        yield "CPU"
        return
    saved_type = prefs.compute_device_type
    saved_use = {d.id: d.use for d in prefs.devices}
    chosen = None
    try:
        for backend in ([saved_type] if saved_type not in ("", "NONE") else []) + ["OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"]:
            try:
                with quiet_blender_output():
                    prefs.compute_device_type = backend
                    prefs.get_devices_for_type(backend)
            except (TypeError, ValueError, AttributeError):
                continue
            gpus = [d for d in prefs.devices if d.type == backend]
            if gpus:
                for d in gpus:
                    d.use = True
                chosen = backend
                break
        if chosen is None and requested == "gpu":
            raise UserError("GPU rendering requested but Cycles finds no GPU (OptiX, CUDA, HIP, oneAPI, Metal); "
                            "use the CPU")
        yield "GPU" if chosen else "CPU"
    finally:
        try:
            prefs.compute_device_type = saved_type
            for d in prefs.devices:
                if d.id in saved_use:
                    d.use = saved_use[d.id]
        except (TypeError, ValueError):
            pass


def _setup_render(scene, settings: RenderSettings, cycles_device: str) -> None:
    r = scene.render
    r.resolution_x = r.resolution_y = settings.resolution
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = True
    r.use_compositing = True
    r.use_sequencer = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    scene.view_layers[0].use_pass_z = True
    if settings.engine == "cycles":
        r.engine = "CYCLES"
        scene.cycles.device = cycles_device
        scene.cycles.samples = settings.samples
        scene.cycles.use_adaptive_sampling = True
        scene.cycles.use_denoising = False
        scene.cycles.max_bounces = 4
        if settings.passes:
            scene.cycles.filter_width = render_passes.PASS_FILTER_WIDTH
    else:
        r.engine = "BLENDER_WORKBENCH"
        shading = scene.display.shading
        shading.light = "STUDIO"
        shading.color_type = "TEXTURE"
        shading.show_backface_culling = False
        scene.display.render_aa = "8"


def _setup_compositor(scene, out_dir: Path):
    """File Output nodes: colour as 8-bit RGBA PNG (view transform applied), depth as float EXR."""
    tree = bpy.data.node_groups.new("UniPixie views", "CompositorNodeTree")
    scene.compositing_node_group = tree
    layers = tree.nodes.new("CompositorNodeRLayers")
    layers.scene = scene
    colour = file_output_node(tree, out_dir, "PNG", "RGBA", "8")
    colour.save_as_render = True
    colour.file_output_items.new("RGBA", "rgba")
    tree.links.new(layers.outputs["Image"], colour.inputs["rgba"])
    depth = file_output_node(tree, out_dir, "OPEN_EXR", "RGB", "32")
    depth.file_output_items.new("FLOAT", "depth")
    tree.links.new(layers.outputs["Depth"], depth.inputs["depth"])
    return colour, depth


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0


def _read_exr(path: Path) -> np.ndarray:
    """(H, W, channels) float32 pixels of an EXR file, rows top-down (as written, no colour management)."""
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = img.size
        px = np.empty(w * h * img.channels, dtype=np.float32)
        img.pixels.foreach_get(px)
        return px.reshape(h, w, img.channels)[::-1].copy()     # Blender stores rows bottom-up
    finally:
        bpy.data.images.remove(img)


def _read_exr_channel0(path: Path) -> np.ndarray:
    return _read_exr(path)[..., 0]


def _find_output(out_dir: Path, prefix: str, item: str, suffix: str) -> Path:
    found = sorted(out_dir.glob(f"{prefix}{item}*{suffix}"))
    if not found:
        raise RuntimeError(f"the renderer wrote no {item} image for {prefix!r} in {out_dir}: "
                           f"{sorted(p.name for p in out_dir.iterdir())}")
    return found[-1]


def preload_before_opengl() -> None:
    """Import open_clip (torch, torchvision and triton's bundled LLVM) before Blender's OpenGL starts.

    With bpy 5.0.1 on Linux under Mesa, importing triton *after* a Workbench render (an EGL context on
    llvmpipe, which has its own LLVM) kills the process with a segmentation fault; importing it before is
    fine.  Workbench renders therefore load it first when it is installed.
    """
    import importlib
    import importlib.util

    if importlib.util.find_spec("open_clip") is not None:
        importlib.import_module("open_clip")


def render_job(objects, settings: RenderSettings | None = None) -> Generator[tuple[float, str], None, Views]:
    """Render the subject's views one by one; yields (fraction done, status) after each view and returns
    :class:`~unipixie.core.types.Views` (see module docstring).  Closing the generator (Esc) stops after
    the current view and removes everything it created."""
    settings = settings or RenderSettings()
    objs = geometry_objects(_as_list(objects))
    if settings.engine == "workbench":
        preload_before_opengl()
    before = snapshot_ids()
    tmp_dir = Path(tempfile.mkdtemp(prefix="unipixie-views-"))
    try:
        with evaluated_meshes(objs) as meshes:
            verts, _ = _collect_triangles(meshes)
            norm = Normalisation.from_points(verts)
            N = norm.to_normalised_matrix
            radius = float(np.max(np.linalg.norm(norm.to_normalised(verts), axis=1)))
            scene = bpy.data.scenes.new("UniPixie views")
            if settings.passes:
                render_passes.prepare_pass_materials(meshes)
            for obj, mesh, matrix in meshes:
                copy = bpy.data.objects.new(f"UniPixie view copy {obj.name}", mesh)
                copy.matrix_world = _matrix(N @ matrix)
                scene.collection.objects.link(copy)
            c2w, K, distance, lens, sensor = camera_rig(settings.view_count, max(radius, 1e-3), settings.resolution,
                                                        settings.fov_degrees)
            cam_data = bpy.data.cameras.new("UniPixie camera")
            cam_data.type = "PERSP"
            cam_data.sensor_fit = "HORIZONTAL"
            cam_data.sensor_width = sensor
            cam_data.lens = lens
            cam_data.shift_x = cam_data.shift_y = 0.0
            cam_data.clip_start = max(1e-3, distance - radius - 0.5)
            cam_data.clip_end = distance + radius + 1.0
            cam = bpy.data.objects.new("UniPixie camera", cam_data)
            scene.collection.objects.link(cam)
            scene.camera = cam
            _setup_world(scene)
            yield 0.0, f"rendering {settings.view_count} views ({settings.engine}, {settings.resolution} px)"
            with _cycles_device(settings.device if settings.engine == "cycles" else "cpu") as cycles_device:
                _setup_render(scene, settings, cycles_device)
                colour_node, depth_node = _setup_compositor(scene, tmp_dir)
                pass_node = None
                if settings.passes:
                    tree = scene.compositing_node_group
                    layers = next(n for n in tree.nodes if n.bl_idname == "CompositorNodeRLayers")
                    pass_node = render_passes.setup_pass_outputs(scene, tree, layers, tmp_dir)
                V, R = settings.view_count, settings.resolution
                passes = {name: np.zeros((V, R, R, c), dtype=np.float32)
                          for name, c in render_passes.PASS_CHANNELS.items()} if settings.passes else {}
                images = np.empty((V, R, R, 3), dtype=np.float32)
                depths = np.empty((V, R, R), dtype=np.float32)
                bg = np.asarray(settings.background, dtype=np.float32)
                for v in range(V):
                    cam.matrix_world = _matrix(c2w[v])
                    prefix = f"view{v:03d}_"
                    colour_node.file_name = prefix
                    depth_node.file_name = prefix
                    if pass_node is not None:
                        pass_node.file_name = prefix
                    with quiet_blender_output() as log_tail:
                        try:
                            bpy.ops.render.render(write_still=False, scene=scene.name)
                        except RuntimeError as exc:
                            raise UserError(f"Blender failed to render view {v}: {str(exc).strip()} "
                                            f"(last output: {log_tail()})") from None
                    rgba = _read_png(_find_output(tmp_dir, prefix, "rgba", ".png"))
                    alpha = rgba[..., 3:4]
                    images[v] = rgba[..., :3] * alpha + bg * (1.0 - alpha)
                    z = _read_exr_channel0(_find_output(tmp_dir, prefix, "depth", ".exr"))
                    depths[v] = np.where((z > 0) & (z < cam_data.clip_end), z, np.inf)
                    if pass_node is not None:
                        raw = render_passes.read_passes(tmp_dir, prefix, _read_exr, _find_output)
                        for name, px in render_passes.unpremultiplied(raw, rgba[..., 3], depths[v]).items():
                            passes[name][v] = px
                    yield (v + 1) / V, f"view {v + 1}/{V}"
        meta = {"engine": settings.engine, "render_settings": settings.key(),
                "objects": [o.name for o in objs], "normalisation": norm.to_dict(),
                "camera_distance": distance, "subject_radius": radius, "lens_mm": lens}
        return Views(images=images, depth=depths, intrinsics=K, cam_to_world=c2w, normalisation=N, meta=meta,
                     passes=passes)
    finally:
        remove_new_ids(before)
        shutil.rmtree(tmp_dir, ignore_errors=True)


def render_views(objects, settings: RenderSettings | None = None, progress=None) -> Views:
    """Render the subject's views to the end (see :func:`render_job`); ``progress`` gets a step per view
    and can cancel."""
    return run_job(render_job(objects, settings), progress)


def benchmark_object(scene=None):
    """A procedural textured object for benchmarks, linked into ``scene`` (default: the current one; the
    caller removes it): Suzanne subdivided twice (about 8 000 faces) with a noise-texture base colour."""
    import bmesh

    mesh = bpy.data.meshes.new("bench suzanne")
    obj = bpy.data.objects.new("bench suzanne", mesh)
    (scene or bpy.context.scene).collection.objects.link(obj)
    bm = bmesh.new()
    bmesh.ops.create_monkey(bm)
    bm.to_mesh(mesh)
    bm.free()
    obj.modifiers.new("subdivide", "SUBSURF").levels = 2
    mat = bpy.data.materials.new("bench noise")
    tree = mat.node_tree
    if tree is None:
        mat.use_nodes = True
        tree = mat.node_tree
    bsdf = next(n for n in tree.nodes if n.type == "BSDF_PRINCIPLED")
    noise = tree.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 6.0
    tree.links.new(noise.outputs["Color"], bsdf.inputs["Base Color"])
    mesh.materials.append(mat)
    return obj
