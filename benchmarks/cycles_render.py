"""The Blender Cycles side of `benchmarks.bench_cycles`: runs under a Python that has `bpy` (Blender as a module).

`bpy` pins `numpy<2` and jaxfog's JAX needs `numpy>=2`, so this file lives in its own interpreter
(`python3.11 -m venv V && V/bin/pip install bpy`) and imports only `bpy`, NumPy and the standard library, never
jaxfog. Run as a script, not as a module of the `benchmarks` package:

    V/bin/python benchmarks/cycles_render.py JOB.json OUT.npz

`JOB.json` holds `{"scene": ..., "jobs": [...]}`: `scene` is the plain dict of Cycles parameters that
`benchmarks.bench_cycles.to_cycles` writes (Blender's Z-up coordinates, matrices row by row, powers in W, angles in
radians, densities in 1/m); each job is `{"name", "settings": {"volume_sampling", "guiding"}, "spp", "seeds"}` and
renders one image per seed. `OUT.npz` gets, per job `k`, `images_k` `(n, H, W, 3)` float32 (linear, row 0 at the
top), `times_k` (s: each `bpy.ops.render.render` call), `warmup_k` (s: one discarded render of the job's settings,
which builds the scene's BVH and kernels on the first job), and `setup_s` (building the scene), `version`, `threads`.

The timed render writes nothing; the pixels are then saved by `save_render` as a 32-bit float OpenEXR in a
temporary folder and read back with `bpy.data.images.load` (outside the timing).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np


def _matrix(rows):
    from mathutils import Matrix

    return Matrix([list(r) for r in rows])


def _link(nt, a, out, b, inp):
    nt.links.new(a.outputs[out], b.inputs[inp])


def _diffuse_material(name: str, reflectance):
    import bpy

    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    d = nt.nodes.new("ShaderNodeBsdfDiffuse")
    d.inputs["Color"].default_value = (*reflectance, 1.0)
    d.inputs["Roughness"].default_value = 0.0  # Lambert
    o = nt.nodes.new("ShaderNodeOutputMaterial")
    _link(nt, d, "BSDF", o, "Surface")
    return m


def _mesh_object(name: str, verts, faces, material, smooth: bool):
    import bpy

    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(v) for v in verts], [], [tuple(f) for f in faces])
    me.update()
    if smooth:
        me.shade_smooth()
    me.materials.append(material)
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _icosphere(subdivisions: int):
    """Unit icosphere vertices and triangles (bmesh), for a sphere of many flat triangles with smooth normals."""
    import bmesh

    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=subdivisions, radius=1.0)
    verts = [tuple(v.co) for v in bm.verts]
    bm.verts.index_update()
    faces = [tuple(v.index for v in f.verts) for f in bm.faces]
    bm.free()
    return verts, faces


def build_scene(p: dict) -> None:
    """Empty the default file and build the scene of `p` (see `benchmarks.bench_cycles.to_cycles`)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    _render_settings(scene, p)
    _camera(scene, p["camera"])
    _world(scene, p["volume"])
    _shapes(p["shapes"])
    _lights(scene, p["lights"])


def _render_settings(scene, p: dict) -> None:
    """Cycles on the CPU: size, threads, EXR output, box filter, no denoising / adaptive sampling / clamping, the
    bounce limits of `p`."""
    r, c = scene.render, scene.cycles
    r.engine = "CYCLES"
    c.device = "CPU"
    r.resolution_x, r.resolution_y, r.resolution_percentage = p["width"], p["height"], 100
    r.threads_mode, r.threads = "FIXED", int(p["threads"])
    r.use_persistent_data = True  # keep the BVH and kernels between renders (the timed renders are the sampling)
    r.film_transparent = False
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_depth = "32"
    r.image_settings.exr_codec = "NONE"
    c.pixel_filter_type, c.filter_width = "BOX", float(p["filter_width"])
    c.use_denoising = False
    c.use_adaptive_sampling = False
    c.use_light_tree = bool(p["use_light_tree"])
    c.light_sampling_threshold = 0.0  # no probabilistic termination of light samples
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0  # no clamping (it biases)
    c.use_animated_seed = False
    b = p["bounces"]
    c.max_bounces, c.diffuse_bounces, c.glossy_bounces = b["max"], b["diffuse"], b["glossy"]
    c.transmission_bounces, c.volume_bounces, c.transparent_max_bounces = (b["transmission"], b["volume"],
                                                                          b["transparent"])
    c.min_light_bounces = c.min_transparent_bounces = 0
    c.caustics_reflective = c.caustics_refractive = True
    if "volume_biased" in c.bl_rna.properties:
        c.volume_biased = False


def _camera(scene, p: dict) -> None:
    """The camera of `p` (`fov_x`: horizontal field of view, `matrix`)."""
    import bpy

    cam = bpy.data.cameras.new("camera")
    cam.type, cam.sensor_fit, cam.angle = "PERSP", "HORIZONTAL", float(p["fov_x"])
    cam.clip_start, cam.clip_end = 1e-3, 1e5
    cam_ob = bpy.data.objects.new("camera", cam)
    scene.collection.objects.link(cam_ob)
    cam_ob.matrix_world = _matrix(p["matrix"])
    scene.camera = cam_ob


def _world(scene, v: dict | None) -> None:
    """The world: black background, the fog `v` (None: none) as a world volume (fills all space outside the
    objects)."""
    import bpy

    world = bpy.data.worlds.new("world")
    scene.world = world
    world.color = (0.0, 0.0, 0.0)
    world.use_nodes = True
    nt = world.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    bg.inputs["Strength"].default_value = 0.0
    _link(nt, bg, "Background", out, "Surface")
    if v is not None:
        sc = nt.nodes.new("ShaderNodeVolumeScatter")
        sc.inputs["Color"].default_value = (*v["scatter_color"], 1.0)
        sc.inputs["Density"].default_value = float(v["scatter_density"])
        sc.inputs["Anisotropy"].default_value = float(v["anisotropy"])
        ab = nt.nodes.new("ShaderNodeVolumeAbsorption")
        ab.inputs["Color"].default_value = (*v["absorption_color"], 1.0)
        ab.inputs["Density"].default_value = float(v["absorption_density"])
        add = nt.nodes.new("ShaderNodeAddShader")
        nt.links.new(sc.outputs[0], add.inputs[0])
        nt.links.new(ab.outputs[0], add.inputs[1])
        _link(nt, add, "Shader", out, "Volume")


def _shapes(shapes: list) -> None:
    """Each shape (a quad, or a sphere as an icosphere with smooth normals) with its diffuse material."""
    for i, s in enumerate(shapes):
        mat = _diffuse_material(f"bsdf{i}", s["reflectance"])
        if s["type"] == "quad":
            _mesh_object(f"shape{i}", s["vertices"], [(0, 1, 2, 3)], mat, smooth=False)
        elif s["type"] == "sphere":
            verts, faces = _icosphere(int(s["subdivisions"]))
            cx, cy, cz = s["center"]
            rad = float(s["radius"])
            verts = [(cx + rad * x, cy + rad * y, cz + rad * z) for x, y, z in verts]
            _mesh_object(f"shape{i}", verts, faces, mat, smooth=True)
        else:
            raise ValueError(f"shape type {s['type']!r}")


def _lights(scene, lights: list) -> None:
    """Each light: a point or spot of radius 0 (a delta light), its power, color and matrix."""
    import bpy

    for i, li in enumerate(lights):
        lt = bpy.data.lights.new(f"light{i}", li["type"])
        lt.energy = float(li["power"])
        lt.color = tuple(li["color"])
        lt.shadow_soft_size = 0.0  # a point: a delta light, as in jaxfog and Mitsuba
        for attr, val in (("use_soft_falloff", False), ("normalize", True), ("exposure", 0.0)):
            if attr in lt.bl_rna.properties:
                setattr(lt, attr, val)
        if li["type"] == "SPOT":
            lt.spot_size, lt.spot_blend = float(li["spot_size"]), float(li["spot_blend"])
        ob = bpy.data.objects.new(f"light{i}", lt)
        scene.collection.objects.link(ob)
        ob.matrix_world = _matrix(li["matrix"])


def apply_settings(settings: dict) -> None:
    """Cycles' sampling options for one job: the world volume's `volume_sampling` (DISTANCE, EQUIANGULAR,
    MULTIPLE_IMPORTANCE) and path guiding (`guiding`: "off", "volume", "surface", "both"; CPU only)."""
    import bpy

    scene = bpy.context.scene
    scene.world.cycles.volume_sampling = settings["volume_sampling"]
    g = settings.get("guiding", "off")
    c = scene.cycles
    c.use_guiding = g != "off"
    c.use_volume_guiding = g in ("volume", "both")
    c.use_surface_guiding = g in ("surface", "both")


def render_once(spp: int, seed: int, tmpdir: str) -> tuple[np.ndarray, float]:
    """One render of `spp` samples with `seed`: the linear RGB image `(H, W, 3)` (row 0 at the top) and the wall
    time of the `bpy.ops.render.render` call."""
    import bpy

    scene = bpy.context.scene
    scene.cycles.samples = int(spp)
    scene.cycles.seed = int(seed)
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=False)
    dt = time.perf_counter() - t0
    path = os.path.join(tmpdir, "render.exr")
    bpy.data.images["Render Result"].save_render(filepath=path)
    img = bpy.data.images.load(path, check_existing=False)
    w, h = img.size
    px = np.empty(w * h * img.channels, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    px = px.reshape(h, w, -1)[::-1, :, :3]  # Blender's rows run bottom to top
    return np.ascontiguousarray(px), dt


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="cycles_render.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("job", metavar="JOB.json", help="the scene and the jobs (benchmarks.bench_cycles.run_cycles)")
    ap.add_argument("out", metavar="OUT.npz", help="where the images and times go")
    args = ap.parse_args(argv)
    with open(args.job) as f:
        job = json.load(f)
    import bpy

    t0 = time.perf_counter()
    build_scene(job["scene"])
    setup = time.perf_counter() - t0
    out = {"setup_s": setup, "version": bpy.app.version_string, "threads": bpy.context.scene.render.threads}
    quiet = job.get("quiet", False)
    with tempfile.TemporaryDirectory() as tmp:
        for k, jb in enumerate(job["jobs"]):
            apply_settings(jb["settings"])
            _, warm = render_once(jb["spp"], 987_654_321 + k, tmp)
            images, times = [], []
            for seed in jb["seeds"]:
                img, dt = render_once(jb["spp"], seed, tmp)
                images.append(img)
                times.append(dt)
                if not quiet:
                    print(f"cycles {jb['name']}: seed {seed}, {jb['spp']} spp in {dt:.2f} s, mean {img.mean():.4g}",
                          file=sys.stderr, flush=True)
            out[f"images_{k}"] = np.stack(images).astype(np.float32)
            out[f"times_{k}"] = np.asarray(times)
            out[f"warmup_{k}"] = warm
    tmp_out = args.out + ".tmp.npz"
    np.savez(tmp_out, **out)
    os.replace(tmp_out, args.out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
