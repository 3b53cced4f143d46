"""Multi-view rendering through real bpy: cameras and depth against ray casts, colour, lifting of a rendered
colour that encodes x, the user's scene left untouched, cancellation, bad input."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.blender
trimesh = pytest.importorskip("trimesh")


def _emission_x_material(bpy, name="x ramp"):
    """Emission colour (x + 0.5, 0.2, 0.8) with x the world x of the shading point (the render scene is the
    normalised cube, so x in [-0.5, 0.5])."""
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree if mat.node_tree is not None else None
    if tree is None:
        mat.use_nodes = True
        tree = mat.node_tree
    tree.nodes.clear()
    geo = tree.nodes.new("ShaderNodeNewGeometry")
    sep = tree.nodes.new("ShaderNodeSeparateXYZ")
    add = tree.nodes.new("ShaderNodeMath")
    add.operation = "ADD"
    add.inputs[1].default_value = 0.5
    comb = tree.nodes.new("ShaderNodeCombineXYZ")
    comb.inputs["Y"].default_value = 0.2
    comb.inputs["Z"].default_value = 0.8
    emit = tree.nodes.new("ShaderNodeEmission")
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(geo.outputs["Position"], sep.inputs[0])
    tree.links.new(sep.outputs["X"], add.inputs[0])
    tree.links.new(add.outputs[0], comb.inputs["X"])
    tree.links.new(comb.outputs[0], emit.inputs["Color"])
    tree.links.new(emit.outputs[0], out.inputs["Surface"])
    return mat, emit


def _srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _raycast_depth(mesh, views):
    V, H, W = views.depth.shape
    K = views.intrinsics[0]
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(jj - K[0, 2]) / K[0, 0], -(ii - K[1, 2]) / K[1, 1], -np.ones_like(jj)], -1).reshape(-1, 3)
    out = np.full((V, H * W), np.inf)
    for v in range(V):
        c2w = views.cam_to_world[v]
        dirs = d_cam @ c2w[:3, :3].T
        origins = np.tile(c2w[:3, 3], (len(dirs), 1))
        loc, ray, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
        out[v, ray] = (loc - origins[ray]) @ (-c2w[:3, 2])
    return out.reshape(V, H, W)


@pytest.fixture
def x_sphere(blender):
    bpy = blender
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, segments=48, ring_count=24, location=(1.0, 2.0, 3.0))
    obj = bpy.context.active_object
    obj.scale = (1.0, 1.0, 1.6)                           # not a sphere: normalisation must not distort it
    mat, _ = _emission_x_material(bpy)
    obj.data.materials.append(mat)
    return obj


def test_cycles_views_match_ray_cast_depth_and_encode_x(blender, x_sphere):
    from unipixie.core import lift
    from unipixie.core.blender_io.render import RenderSettings, describe_subject, render_views
    from unipixie.core.normalise import Normalisation

    views = render_views(x_sphere, RenderSettings(view_count=8, resolution=64, engine="cycles", samples=4))
    assert views.images.shape == (8, 64, 64, 3) and views.depth.shape == (8, 64, 64)
    norm = Normalisation.from_matrix(views.normalisation)
    subject = describe_subject([x_sphere])
    # world bbox: centre (1, 2, 3), extents 1.4 x 1.4 x 2.24 m -> scale 2.24
    assert np.allclose(norm.centre, (1, 2, 3), atol=1e-4) and norm.scale == pytest.approx(2.24, rel=1e-3)
    mesh = trimesh.Trimesh(norm.to_normalised(subject.vertices), subject.faces, process=False)

    # depth is z-depth in normalised units, the cameras' intrinsics/extrinsics are the ones used (1e-3 ≈ 1/16 voxel)
    ray = _raycast_depth(mesh, views)
    fg = np.isfinite(views.depth)
    assert np.array_equal(fg, np.isfinite(ray))
    assert 0.3 < fg.mean() < 0.8
    assert np.median(np.abs(views.depth[fg] - ray[fg])) < 1e-3

    # background composited to white (away from the anti-aliased silhouette); colour = sRGB(x + 0.5, 0.2, 0.8)
    from scipy import ndimage

    far_background = ndimage.binary_erosion(~fg, structure=np.ones((1, 5, 5), bool), border_value=1)
    assert far_background.mean() > 0.1 and np.allclose(views.images[far_background], 1.0)
    green = _srgb_to_linear(views.images[..., 1])[fg]
    assert np.median(np.abs(green - 0.2)) < 0.01

    # lifting the rendered colour recovers x at surface voxels
    occ = lift.occupancy_from_mesh(mesh).occupancy
    res = lift.lift_features(views, views.images, occ)
    idx = np.argwhere(occ)
    centres = lift.unit_cube_grid().centres(idx)
    seen = res.views_per_voxel > 0
    x_est = _srgb_to_linear(res.features[:, 0].astype(np.float64)) - 0.5
    err = np.abs(x_est - centres[:, 0])[seen]
    assert seen.sum() > 0.95 * lift.surface_mask(occ).sum()
    # tolerance: a surface voxel's centre lies within a voxel (1/64 = 0.016) of the surface it is painted from
    assert np.mean(err) < 0.012 and np.percentile(err, 95) < 0.03


def test_workbench_renders_depth_and_the_objects_colour(blender):
    bpy = blender
    from unipixie.core.blender_io.render import RenderSettings, describe_subject, render_views
    from unipixie.core.normalise import Normalisation

    bpy.ops.mesh.primitive_cube_add(size=2.0)
    cube = bpy.context.active_object
    mat = bpy.data.materials.new("red")
    mat.diffuse_color = (0.8, 0.05, 0.05, 1.0)            # Workbench shows the viewport colour
    cube.data.materials.append(mat)
    views = render_views(cube, RenderSettings(view_count=2, resolution=48, engine="workbench"))
    fg = np.isfinite(views.depth)
    assert fg.mean() > 0.2
    red, green = views.images[..., 0][fg], views.images[..., 1][fg]
    assert np.median(red - green) > 0.2                   # reddish, lit
    subject = describe_subject([cube])
    norm = Normalisation.from_matrix(views.normalisation)
    mesh = trimesh.Trimesh(norm.to_normalised(subject.vertices), subject.faces, process=False)
    ray = _raycast_depth(mesh, views)
    both = fg & np.isfinite(ray)
    assert both.sum() > 0.95 * fg.sum() and np.median(np.abs(views.depth[both] - ray[both])) < 1e-3


def _scene_state(bpy):
    scene = bpy.context.scene
    r = scene.render
    state = {
        "scene": scene.name,
        "scenes": sorted(bpy.data.scenes.keys()),
        "render": (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.filepath, r.film_transparent,
                   scene.view_settings.view_transform, scene.camera.name if scene.camera else None,
                   scene.world.name if scene.world else None, scene.frame_current),
        "selected": sorted(o.name for o in bpy.context.view_layer.objects if o.select_get()),
        "active": bpy.context.view_layer.objects.active.name if bpy.context.view_layer.objects.active else None,
        "objects": {o.name: (o.type, tuple(np.round(np.array(o.matrix_world), 9).ravel()), o.data.name if o.data else None,
                             len(o.modifiers)) for o in bpy.data.objects},
        "meshes": {m.name: (len(m.vertices), len(m.polygons), m.users) for m in bpy.data.meshes},
        "materials": {m.name: m.users for m in bpy.data.materials},
    }
    for prop in bpy.data.bl_rna.properties:
        if prop.type == "COLLECTION" and prop.identifier not in ("window_managers", "screens", "workspaces"):
            state[f"count:{prop.identifier}"] = len(getattr(bpy.data, prop.identifier))
    return state


def test_rendering_leaves_the_users_scene_untouched_and_cancels_cleanly(blender):
    bpy = blender
    from unipixie.core.blender_io.render import RenderSettings, render_job, render_views
    from unipixie.core.errors import CancelledError
    from unipixie.core.progress import Progress

    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = 320, 180
    scene.render.filepath = "//my_render_"
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "AgX"
    bpy.ops.object.camera_add(location=(5, -5, 3))
    scene.camera = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(location=(3, 0, 0))
    other = bpy.context.active_object
    bpy.ops.mesh.primitive_monkey_add(location=(0, 1, 0))
    subject = bpy.context.active_object
    subject.modifiers.new("smooth", "SUBSURF")
    subject.data.materials.append(_emission_x_material(bpy)[0])
    other.select_set(True)
    subject.select_set(True)
    bpy.context.view_layer.objects.active = subject
    before = _scene_state(bpy)

    views = render_views(subject, RenderSettings(view_count=3, resolution=32, samples=2))
    assert views.count == 3 and np.isfinite(views.depth).any()
    assert _scene_state(bpy) == before

    job = render_job(subject, RenderSettings(view_count=5, resolution=32, samples=2))
    next(job)                                  # set up
    next(job)                                  # first view
    job.close()                                # Esc in the panel
    assert _scene_state(bpy) == before

    steps = []

    def cancel_after_two(fraction, status):
        steps.append(fraction)
        if len(steps) == 2:
            progress.cancel()

    progress = Progress(total=10, callback=cancel_after_two)
    with pytest.raises(CancelledError):
        render_views(subject, RenderSettings(view_count=6, resolution=32, samples=2), progress)
    assert len(steps) == 2 and _scene_state(bpy) == before


def test_objects_without_faces_or_geometry_are_refused(blender):
    bpy = blender
    from unipixie.core.blender_io.render import describe_subject, render_views
    from unipixie.core.errors import UserError

    mesh = bpy.data.meshes.new("points")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1)], [])
    obj = bpy.data.objects.new("points", mesh)
    bpy.context.scene.collection.objects.link(obj)
    with pytest.raises(UserError, match="no faces"):
        render_views(obj)
    empty = bpy.data.objects.new("empty", None)
    bpy.context.scene.collection.objects.link(empty)
    with pytest.raises(UserError, match="no object with geometry"):
        describe_subject([empty])


def test_fingerprint_follows_geometry_and_materials(blender):
    bpy = blender
    from unipixie.core.blender_io.render import describe_subject

    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    mat, emit = _emission_x_material(bpy)
    cube.data.materials.append(mat)
    first = describe_subject([cube]).fingerprint
    assert describe_subject([cube]).fingerprint == first
    emit.inputs["Strength"].default_value = 2.0
    changed_material = describe_subject([cube]).fingerprint
    assert changed_material != first
    cube.data.vertices[0].co.x += 0.1
    assert describe_subject([cube]).fingerprint not in (first, changed_material)
    img = bpy.data.images.new("tex", 4, 4)
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    with_image = describe_subject([cube]).fingerprint
    img.pixels[0] = 0.5
    img.update()
    assert describe_subject([cube]).fingerprint != with_image


def test_workbench_then_torch_in_a_fresh_process_does_not_crash(tmp_path):
    """Regression: importing triton (via open_clip -> torchvision -> torch._dynamo) after a Workbench render
    segfaulted the process (Mesa's llvmpipe and triton each bring an LLVM); Workbench renders preload it."""
    import subprocess
    import sys

    pytest.importorskip("bpy")
    code = ("import bpy\n"
            "from unipixie.core.blender_io.render import RenderSettings, render_views\n"
            "bpy.ops.mesh.primitive_cube_add()\n"
            "render_views(bpy.context.active_object, RenderSettings(view_count=1, resolution=32, engine='workbench'))\n"
            "import open_clip\n"
            "from unipixie.core.clip_features import offline_extractor\n"
            "print('features', tuple(offline_extractor()(__import__('numpy').zeros((1, 32, 32, 3))).shape))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "features (1, 14, 14, 32)" in proc.stdout
