"""Bad inputs refused before any work, and hard inputs given the right result: mesh files and arrays, the scene
schema's ranges shared with the Modules, a glass object across a bounded fog's face, the render and fit command
lines' outputs (nothing a user has is overwritten or lost) and the fit's arguments. Each row checks the one-line
message (file / key / argument, the value, what is valid) and that the refusal comes before anything is rendered:
the renderer and the fit are replaced by functions that fail the test if called."""

from __future__ import annotations

import json
import os
import shutil
import stat

import jax
import numpy as np
import pytest

import jaxfog as jf
from helpers import SPOT_FOG, spot_fog, spot_fog_dict
from jaxfog import _render
from jaxfog._cli import main as cli_main
from jaxfog._mesh import MeshError, read_mesh
from jaxfog._validate import (DROPLET_DIAMETER_RANGE, G_RANGE, HEIGHT_SCALE_RANGE, MAX_RR_DEPTH, RR_DEPTH_RANGE,
                              SPOT_CUTOFF_RANGE, Range, check_range)

from test_bad_inputs import TINY, _one_line_error, no_render  # noqa: F401  (the shared refusal helpers and fixture)


def _raises(call, exc, *parts):
    with pytest.raises(exc) as info:
        call()
    text = str(info.value)
    assert "\n" not in text, text
    for part in parts:
        assert part in text, text
    return text


# ------------------------------------------------------------------------------------------------- mesh files
PLY_HEAD = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
            "element face {n}\nproperty list uchar int vertex_indices\nend_header\n")
PLY_BODY = "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"


def _binary_ply(tmp_path) -> bytes:
    jf.write_ply(tmp_path / "b.ply", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    return (tmp_path / "b.ply").read_bytes()


MESH_FILE_ROWS = [
    # (id, file contents (str: ASCII, a function of tmp_path: bytes), substrings of the message)
    ("ASCII PLY with more faces than declared", PLY_HEAD.format(n=1) + PLY_BODY + "3 0 2 1\n",
     ["PLY data has 4 values after the records the header declares (3 vertex, 1 face)", "exactly the declared"]),
    ("binary PLY with more faces than declared",
     lambda tp: _binary_ply(tp) + bytes([3]) + np.array([0, 2, 1], "<i4").tobytes(),
     ["PLY data has 13 bytes after the records the header declares (3 vertex, 1 face)"]),
    ("ASCII PLY cut inside its last face", PLY_HEAD.format(n=1) + PLY_BODY[:-3],
     ["PLY data ends inside face 0 of 1 (vertex_indices declares 3 values, 2 remain)"]),
    ("element face -1", PLY_HEAD.format(n=-1) + PLY_BODY,
     ["'element face -1': the count -1 is negative; expected an integer >= 0"]),
    ("binary element face -1", lambda tp: _binary_ply(tp).replace(b"element face 1", b"element face -1"),
     ["the count -1 is negative"]),
    ("face count 10^20", PLY_HEAD.format(n=10**20) + PLY_BODY,
     ["declares 100000000000000000000 face records, but the file's 26 bytes of data hold at most 13"]),
    ("binary face count 10^20",
     lambda tp: _binary_ply(tp).replace(b"element face 1", b"element face 100000000000000000000"),
     ["declares 100000000000000000000 face records"]),
    ("end_header without a newline, no data", PLY_HEAD.format(n=1)[:-1],
     ["declares 3 vertex records, but the file's 0 bytes of data hold at most 0"]),
    ("binary end_header without a newline",
     lambda tp: _binary_ply(tp).replace(b"end_header\n", b"end_header"),
     ["end_header is followed by", "not a newline; expected end_header on a line of its own"]),
    ("float face indices", PLY_HEAD.format(n=1).replace("uchar int", "uchar float") + PLY_BODY,
     ["face property vertex_indices is not a list of integers"]),
]


@pytest.mark.parametrize("content, parts", [r[1:] for r in MESH_FILE_ROWS], ids=[r[0] for r in MESH_FILE_ROWS])
def test_mesh_files_refused(tmp_path, content, parts):
    path = tmp_path / "bad.ply"
    if callable(content):
        path.write_bytes(content(tmp_path))
    else:
        path.write_text(content)
    text = _raises(lambda: read_mesh(path), MeshError, str(path), *parts)
    # in a scene file: a SceneError naming the scene file and the key as well
    data = spot_fog_dict()
    data["shapes"].append({"type": "mesh", "file": "bad.ply", "bsdf": {"type": "diffuse", "reflectance": 0.5}})
    (tmp_path / "s.json").write_text(json.dumps(data))
    scene_text = _raises(lambda: jf.load_scene(tmp_path / "s.json"), jf.SceneError, "s.json: shapes[2].file: ")
    assert text in scene_text


def test_ply_valid_edge_cases_read(tmp_path):
    """Valid files the stricter reader still reads: no newline after the last value, CRLF line ends."""
    for name, text in (("noeol.ply", PLY_HEAD.format(n=1) + PLY_BODY[:-1]),
                       ("crlf.ply", (PLY_HEAD.format(n=1) + PLY_BODY).replace("\n", "\r\n"))):
        (tmp_path / name).write_bytes(text.encode())
        np.testing.assert_array_equal(read_mesh(tmp_path / name).faces, [[0, 1, 2]])


V3 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
F1 = np.array([[0, 1, 2]])
FROM_ARRAYS_ROWS = [
    ("2-D vertices", lambda: jf.Mesh.from_arrays(np.zeros((6, 2)), F1, jf.Diffuse(0.5)),
     ["Mesh.from_arrays: vertices has shape (6, 2); expected an (n, 3) array of numbers"]),
    ("4-index faces", lambda: jf.Mesh.from_arrays(V3, [[0, 1, 2, 0]], jf.Diffuse(0.5)),
     ["Mesh.from_arrays: faces has shape (1, 4); expected an (n, 3) array of integers"]),
    ("too few normals", lambda: jf.Mesh.from_arrays(V3, F1, jf.Diffuse(0.5), normals=np.zeros((2, 3)) + 1),
     ["Mesh.from_arrays: 2 vertex normals for 3 vertices; expected one normal per vertex"]),
    ("float face indices", lambda: jf.Mesh.from_arrays(V3, F1 + 0.5, jf.Diffuse(0.5)),
     ["Mesh.from_arrays: faces has dtype float64; expected an (n, 3) array of integers"]),
    ("normal index out of range", lambda: jf.Mesh.from_arrays(V3, F1, jf.Diffuse(0.5), normals=[[0, 0, 1]],
                                                              normal_faces=[[0, 0, 1]]),
     ["face 0 has normal indices [0, 0, 1] out of range [0, 0]"]),
]


@pytest.mark.parametrize("call, parts", [r[1:] for r in FROM_ARRAYS_ROWS], ids=[r[0] for r in FROM_ARRAYS_ROWS])
def test_mesh_from_arrays_refuses(call, parts):
    _raises(call, MeshError, *parts)


def _slot_normals(mesh: jf.Mesh) -> np.ndarray:
    """The smooth mesh's vertex normals per used slot, (faces, 3 corners, 3), in the file's face order and each
    face's corners sorted by vertex index (as `Mesh` stores them)."""
    vn = np.asarray(mesh.vn).transpose(0, 3, 1, 2).reshape(-1, 3, 3)
    face = np.asarray(mesh.face)
    out = np.zeros((mesh.n_faces, 3, 3))
    out[face[face >= 0]] = vn[face >= 0]
    return out


def test_obj_normals_are_read_by_the_faces_normal_index(tmp_path):
    """`f 1//2 2//2 3//2`: every corner has normal 2 (not normal i at vertex i, as before); a vertex shared by two
    faces with different normal indices (a hard edge) keeps each face's own normal."""
    n1, n2, n3 = [0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.6, 0.0, 0.8]
    p = tmp_path / "n.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"
                 f"vn {' '.join(map(str, n1))}\nvn {' '.join(map(str, n2))}\nvn {' '.join(map(str, n3))}\n"
                 "f 1//2 2//2 3//2\nf 2/7/3 4//3 3//3\n")
    m = read_mesh(p)
    np.testing.assert_array_equal(m.normal_faces, [[1, 1, 1], [2, 2, 2]])
    expected = np.array([[n2] * 3, [n3] * 3])
    np.testing.assert_allclose(m.corner_normals(), expected)
    mesh = jf.Mesh.from_file(p, jf.Diffuse(0.5), smooth=True)
    np.testing.assert_allclose(_slot_normals(mesh), expected, atol=1e-7)
    # per-vertex normals (a PLY, or from_arrays without normal_faces) still pair normal i with vertex i
    vn = np.array([n1, n2, n3, n1])
    mesh2 = jf.Mesh.from_arrays(m.vertices, m.faces, jf.Diffuse(0.5), normals=vn, smooth=True)
    np.testing.assert_allclose(_slot_normals(mesh2), vn[np.sort(m.faces, axis=1)], atol=1e-7)


def test_obj_without_normal_indices_has_no_normals(tmp_path):
    """`vn` lines that no face refers to are not vertex normals (the OBJ format; Mitsuba reads them the same way)."""
    p = tmp_path / "n.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn 0 0 1\nvn 0 0 1\nf 1 2 3\n")
    assert read_mesh(p).normals is None


# -------------------------------------------------------------------------------- one range, Modules and files
def test_one_range_helper_shared_by_modules_and_files():
    from jaxfog import _scene_io

    assert _scene_io.PHASES["hg"].fields["g"].range is G_RANGE
    assert _scene_io.MEDIA["homogeneous"].fields["g"].range is G_RANGE
    assert _scene_io.MEDIA["height"].fields["height_scale"].range is HEIGHT_SCALE_RANGE
    assert _scene_io.INTEGRATOR.fields["rr_depth"].range is RR_DEPTH_RANGE
    assert _scene_io.LIGHTS["spot"].fields["cutoff_angle"].range is SPOT_CUTOFF_RANGE
    assert _scene_io.PHASES["droplet"].fields["diameter"].range is DROPLET_DIAMETER_RANGE
    assert G_RANGE.text() == "(-1, 1)" and Range(1, None, also=-1).text() == "[1, inf), or -1"
    assert Range(1, None, also=-1).contains(-1) and not Range(1, None, also=-1).contains(0)
    check_range("X", "g", jax.numpy.float32(0.5), G_RANGE)
    jax.jit(lambda g: check_range("X", "g", g, G_RANGE) or g)(2.0)  # traced: skipped
    _raises(lambda: check_range("X", "g", np.float32(1.0), G_RANGE), ValueError,
            "X.g = 1.0 (as float32) is outside the valid range (-1, 1)")


MODULE_ROWS = [
    ("Sphere(radius=-1)", lambda: jf.Sphere((0, 0, 0), -1.0, jf.Diffuse(0.5)), ValueError,
     ["Sphere.radius = -1.0 (as float32) is outside the valid range (0, inf)"]),
    ("Sphere(radius=0)", lambda: jf.Sphere((0, 0, 0), 0.0, jf.Diffuse(0.5)), ValueError,
     ["Sphere.radius = 0.0 (as float32) is outside the valid range (0, inf)"]),
    ("Sphere(center=nan)", lambda: jf.Sphere((0, float("nan"), 0), 1.0, jf.Diffuse(0.5)), ValueError,
     ["Sphere.center = [0.0, nan, 0.0] must be a finite vector"]),
    ("Camera(fov=500)", lambda: jf.Camera(origin=(0, 0, 1), target=(0, 0, 0), up=(0, 1, 0), fov=500, width=4,
                                          height=4), ValueError,
     ["Camera.fov = 500.0 (as float32) is outside the valid range (0, 180)"]),
    ("Camera(up parallel)", lambda: jf.Camera(origin=(0, 0, 1), target=(0, 0, 0), up=(0, 0, 2), fov=40, width=4,
                                              height=4), ValueError,
     ["Camera.up = [0.0, 0.0, 2.0] is parallel to the view direction"]),
    ("Camera(target = origin)", lambda: jf.Camera(origin=(0, 0, 1), target=(0, 0, 1), up=(0, 1, 0), fov=40,
                                                  width=4, height=4), ValueError,
     ["Camera.target = [0.0, 0.0, 1.0] equals origin"]),
    ("Rectangle(edges not perpendicular)", lambda: jf.Rectangle((0, 0, 0), (1, 0, 0), (1, 1, 0), jf.Diffuse(0.5)),
     ValueError, ["Rectangle.edge_v = [1.0, 1.0, 0.0] is not perpendicular to edge_u"]),
    ("Rectangle(zero edge)", lambda: jf.Rectangle((0, 0, 0), (0, 0, 0), (0, 1, 0), jf.Diffuse(0.5)), ValueError,
     ["Rectangle.edge_u = [0.0, 0.0, 0.0] must be a finite, non-zero vector"]),
    ("AreaLight(edges not perpendicular)", lambda: jf.AreaLight((0, 2, 0), (1, 0, 0), (1, 0, 1), 1.0), ValueError,
     ["AreaLight.edge_v = [1.0, 0.0, 1.0] is not perpendicular to edge_u"]),
    ("SpotLight(cutoff_angle=90)", lambda: jf.SpotLight((0, 2, 0), (0, -1, 0), 1.0, 90.0, 10.0), ValueError,
     ["SpotLight.cutoff_angle = 90.0 (as float32) is outside the valid range (0, 90)"]),
    ("HeightFog(height_scale=1e-30)",
     lambda: jf.HeightFog(sigma_0=0.5, height_scale=1e-30, albedo=0.9, phase=jf.HenyeyGreenstein(0.5)), ValueError,
     ["HeightFog.height_scale = 1.0000000031710769e-30 (as float32) is outside the valid range [0.001, 1e+06]"]),
    ("Scene(rr_depth=10**9)", lambda: jf.Scene(camera=spot_fog(width=4, height=4).camera, max_depth=-1,
                                               rr_depth=10**9), ValueError,
     [f"Scene.rr_depth = 1000000000 is outside the valid range [1, {MAX_RR_DEPTH}]"]),
    ("Scene(glass sphere across the fog box's face)",
     lambda: jf.Scene(camera=spot_fog(width=4, height=4).camera,
                      shapes=(jf.Sphere((0.6, 0.5, -0.3), 0.5, jf.Glass()),),
                      medium=jf.HomogeneousMedium(0.5, 0.9, jf.HenyeyGreenstein(0.3),
                                                  bounds=((-1, 0, -1), (1, 0.7, 1)))), ValueError,
     ["Scene.shapes[0]: a glass Sphere straddles a face of the medium's bounds (min [-1.0, 0.0, -1.0], max [1.0, "
      "0.699999988079071, 1.0])", "wholly inside or wholly outside"]),
    ("Scene(glass rectangle across the fog box's face)",
     lambda: jf.Scene(camera=spot_fog(width=4, height=4).camera,
                      shapes=(jf.Rectangle((0, 0, 0), (6, 0, 0), (0, 0, -6), jf.Glass()),),
                      medium=jf.HomogeneousMedium(0.5, 0.9, jf.HenyeyGreenstein(0.3),
                                                  bounds=((-1, -1, -1), (1, 2, 1)))), ValueError,
     ["Scene.shapes[0]: a glass Rectangle straddles a face of the medium's bounds"]),
    ("Scene(glass mesh across the fog box's face)",
     lambda: jf.Scene(camera=spot_fog(width=4, height=4).camera,
                      shapes=(jf.Mesh.from_arrays([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], jf.Glass()),),
                      medium=jf.HomogeneousMedium(0.5, 0.9, jf.HenyeyGreenstein(0.3),
                                                  bounds=((-1, 0.5, -1), (1, 2, 1)))), ValueError,
     ["Scene.shapes[0]: a glass Mesh straddles a face of the medium's bounds"]),
]


@pytest.mark.parametrize("call, exc, parts", [r[1:] for r in MODULE_ROWS], ids=[r[0] for r in MODULE_ROWS])
def test_modules_refuse_their_python_values(call, exc, parts):
    _raises(call, exc, *parts)


def test_modules_rebuilt_inside_jit_are_not_checked():
    """Traced values are skipped: a Sphere or Camera built inside `jit` from traced arrays is fine."""

    @jax.jit
    def f(r, fov):
        s = jf.Sphere(jax.numpy.zeros(3), r, jf.Diffuse(0.5))
        c = jf.Camera(origin=jax.numpy.ones(3), target=jax.numpy.zeros(3), up=(0, 1, 0), fov=fov, width=2, height=2)
        return s.radius + c.fov

    assert float(f(-1.0, 500.0)) == 499.0


def test_glass_wholly_inside_or_outside_the_fog_box_builds():
    """The Python check of glass against a fog box passes a glass sphere wholly inside (touching a face) or
    outside the box, and diffuse objects anywhere."""
    medium = jf.HomogeneousMedium(0.5, 0.9, jf.HenyeyGreenstein(0.3), bounds=((-1, 0, -1), (1, 1, 1)))
    cam = spot_fog(width=4, height=4).camera
    for center in ((0.0, 0.5, 0.0), (0.0, 2.0, 0.0)):
        jf.Scene(camera=cam, shapes=(jf.Sphere(center, 0.5, jf.Glass()),), medium=medium)
    jf.Scene(camera=cam, shapes=(jf.Sphere((1.0, 1.0, 1.0), 0.5, jf.Diffuse(0.5)),), medium=medium)


SCENE_ROWS = [
    # (id, overrides on spot_fog, substrings of the SceneError)
    ("height_scale 1e-30", ['medium={"type": "height", "sigma_0": 0.5, "height_scale": 1e-30, "albedo": 0.9, '
                            '"g": 0.5}'],
     ["spot_fog.json: medium.height_scale: 1e-30 is out of range; valid range [0.001, 1e+06]"]),
    ("height_scale 1e7", ['medium={"type": "height", "sigma_0": 0.5, "height_scale": 1e7, "albedo": 0.9, "g": 0.5}'],
     ["medium.height_scale: 1e+07 is out of range; valid range [0.001, 1e+06]"]),
    ("rr_depth 10^9 with max_depth -1", ["integrator.max_depth=-1", "integrator.rr_depth=1000000000"],
     ["spot_fog.json: integrator.rr_depth: 1000000000 is out of range; valid range [1, 1024]"]),
    ("glass sphere across the fog box's face",
     ['medium.bounds={"min": [-1, 0, -1], "max": [1, 0.7, 1]}', 'shapes.1.bsdf={"type": "glass"}'],
     ["spot_fog.json: shapes[1]: a glass sphere (center [0.6, 0.5, -0.3], radius 0.5) straddles a face of "
      "medium.bounds (min [-1, 0, -1], max [1, 0.7, 1])", "wholly inside or wholly outside"]),
    ("glass rectangle across the fog box's face",
     ['medium.bounds={"min": [-1, -1, -1], "max": [1, 2, 1]}', 'shapes.0.bsdf={"type": "glass"}'],
     ["spot_fog.json: shapes[0]: a glass rectangle (center [0, 0, 0]) straddles a face of medium.bounds"]),
]


@pytest.mark.parametrize("overrides, parts", [r[1:] for r in SCENE_ROWS], ids=[r[0] for r in SCENE_ROWS])
def test_scene_files_refused(overrides, parts, tmp_path, capsys, no_render):
    _raises(lambda: jf.load_scene(SPOT_FOG, overrides), jf.SceneError, *parts)
    argv = ["render", str(SPOT_FOG), "-o", str(tmp_path / "o.exr"), *TINY]
    for o in overrides:
        argv += ["--set", o]
    assert cli_main(argv) == 1
    err = _one_line_error(capsys)
    for part in parts:
        assert part in err, err


def test_glass_wholly_inside_or_outside_the_fog_box_loads():
    inside = ['medium.bounds={"min": [-1.5, 0, -1.5], "max": [1.5, 1.2, 1.5]}', 'shapes.1.bsdf={"type": "glass"}']
    assert jf.load_scene(SPOT_FOG, inside).scene.medium.bounds is not None
    outside = ['medium.bounds={"min": [-1, 1.1, -1], "max": [1, 2, 1]}', 'shapes.1.bsdf={"type": "glass"}',
               'shapes.0.bsdf={"type": "glass"}']  # the floor touches nothing, the sphere is below the box
    jf.load_scene(SPOT_FOG, outside)


def test_glass_mesh_across_the_fog_box_face_refused(tmp_path):
    jf.write_ply(tmp_path / "t.ply", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    data = spot_fog_dict()
    data["medium"]["bounds"] = {"min": [-1, 0.5, -1], "max": [1, 2, 1]}
    data["shapes"] = [{"type": "mesh", "file": "t.ply", "bsdf": {"type": "glass"}}]
    (tmp_path / "s.json").write_text(json.dumps(data))
    _raises(lambda: jf.load_scene(tmp_path / "s.json"), jf.SceneError,
            "s.json: shapes[0]: a glass mesh (t.ply) straddles a face of medium.bounds")
    data["shapes"][0]["to_world"] = {"translate": [0, 0.6, 0]}
    (tmp_path / "s.json").write_text(json.dumps(data))
    jf.load_scene(tmp_path / "s.json")  # moved wholly inside


# ------------------------------------------------------------------------------------------------- jaxfog render
def test_render_cli_keeps_an_existing_image_when_the_render_fails(tmp_path, capsys, monkeypatch):
    """The finite-value check runs before the write: a NaN render leaves a valid out.exr as it was."""
    out = tmp_path / "out.exr"
    good = np.full((4, 4, 3), 0.25, np.float32)
    jf.write_exr(out, good)
    monkeypatch.setattr(_render, "render", lambda scene, key, spp, **kw: np.full(
        (scene.camera.height, scene.camera.width, 3), np.nan, np.float32))
    assert cli_main(["render", str(SPOT_FOG), "-o", str(out), *TINY]) == 1
    assert "nothing written; the existing file is unchanged" in _one_line_error(capsys)
    np.testing.assert_array_equal(jf.read_exr(out)[0], good)


# ------------------------------------------------------------------------------------------------- fitting.fit
class _FitStarted(Exception):
    """Raised by the stand-in for `fit_views`: the checks passed; carries the starting values."""


@pytest.fixture
def fit_setup(tmp_path, monkeypatch):
    """A 16 x 16 spot_fog scene and a plausible constant target; `fit_views` raises `_FitStarted(init)`."""
    import fitting.fit

    def started(views, names, init, cfg, log=None):
        raise _FitStarted(init)

    monkeypatch.setattr(fitting.fit, "fit_views", started)
    data = spot_fog_dict()
    data["camera"].update(width=16, height=16)
    data["integrator"]["max_depth"] = 2

    def scene(name="scene.json", **medium):
        d = json.loads(json.dumps(data))
        d["medium"].update(medium)
        for k in [k for k, v in medium.items() if v is None]:
            del d["medium"][k]
        (tmp_path / name).write_text(json.dumps(d))
        return str(tmp_path / name)

    target = tmp_path / "t.exr"
    jf.write_exr(target, np.full((16, 16, 3), 0.05, np.float32))
    return {"tmp": tmp_path, "scene": scene, "target": str(target), "data": data}


def _fit(argv, capsys):
    from fitting.fit import main as fit_main

    code = fit_main(argv)
    return code, capsys.readouterr()


def test_fit_refuses_a_scene_without_lights(fit_setup, capsys):
    data = dict(fit_setup["data"], lights=[])
    path = fit_setup["tmp"] / "dark.json"
    path.write_text(json.dumps(data))
    out = fit_setup["tmp"] / "r.json"
    code, cap = _fit([str(path), fit_setup["target"], "--out", str(out)], capsys)
    assert code == 2 and "Traceback" not in cap.err
    assert f"{path}: the scene has no light; expected at least one light" in cap.err.strip().splitlines()[-1]
    assert not out.exists()


FIT_NAME_ROWS = [
    ("the same parameter twice", ["--fit", "sigma_t", "sigma_t:rgb"],
     ["--fit sigma_t sigma_t[r] sigma_t[g] sigma_t[b]: the same parameter twice", "not both"]),
    ("albedo grey and one channel", ["--fit", "albedo", "albedo[g]"], ["--fit albedo albedo[g]: the same parameter"]),
    ("sigma_0 with base_height", ["--fit", "sigma_0", "base_height"],
     ["--fit sigma_0 base_height: no targets determine these two apart: only sigma_0 exp(base_height / "
      "height_scale) enters the image", "fit one of them"]),
]


@pytest.mark.parametrize("argv, parts", [r[1:] for r in FIT_NAME_ROWS], ids=[r[0] for r in FIT_NAME_ROWS])
def test_fit_refuses_parameter_sets(argv, parts, fit_setup, capsys):
    code, cap = _fit([fit_setup["scene"](), fit_setup["target"], "--out", str(fit_setup["tmp"] / "r.json"), *argv],
                     capsys)
    assert code == 2
    err = cap.err.strip().splitlines()[-1]
    for part in parts:
        assert part in err, err


def test_fit_refuses_one_target_twice(fit_setup, capsys):
    scene, t = fit_setup["scene"](), fit_setup["target"]
    link = fit_setup["tmp"] / "same.exr"
    os.symlink(t, link)
    for argv in ([scene, t, t], [scene, t, scene, str(link)]):
        code, cap = _fit([*argv, "--out", str(fit_setup["tmp"] / "r.json")], capsys)
        assert code == 2
        assert "is given twice (targets 1 and 2)" in cap.err, cap.err


def test_fit_refuses_to_overwrite_a_candidate_scene_or_a_read_only_result(fit_setup, capsys):
    scene, t, tmp = fit_setup["scene"](), fit_setup["target"], fit_setup["tmp"]
    cand = fit_setup["scene"]("cand.json")
    before = open(cand).read()
    code, cap = _fit([scene, t, "--candidates", cand, "--out", cand], capsys)
    assert code == 2 and f"--out {cand}: would overwrite the --candidates scene {cand}" in cap.err
    assert open(cand).read() == before
    result = tmp / "r.json"
    result.write_text("{}")
    result.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
    (tmp / "r.png").write_bytes(b"")
    (tmp / "r.png").chmod(0o444)
    code, cap = _fit([scene, t, "--out", str(result)], capsys)
    assert code == 2 and f"--out {result}: {result} is read-only" in cap.err, cap.err
    result.chmod(0o644)
    code, cap = _fit([scene, t, "--out", str(result)], capsys)
    assert code == 2 and f"{tmp / 'r.png'} is read-only" in cap.err, cap.err
    assert result.read_text() == "{}"


START_ROWS = [
    # (id, medium changes, --fit, the start the search is given)
    ("sigma_t 0", dict(sigma_t=0.0), ["sigma_t"], {"sigma_t": np.sqrt(0.2) / np.hypot(4.5, 0.2)}),
    ("albedo 1", dict(albedo=1.0), ["albedo"], {"albedo": 0.995}),
    ("diameter 3 um", dict(g=None, phase={"type": "droplet", "diameter": 3.0}), ["diameter"], {"diameter": 5.5}),
]


@pytest.mark.parametrize("medium, fit, start", [r[1:] for r in START_ROWS], ids=[r[0] for r in START_ROWS])
def test_fit_clamps_a_start_outside_the_range(medium, fit, start, fit_setup, capsys):
    """A scene value outside the fit's range is only a start: clamped into the range, with one line saying so."""
    scene = fit_setup["scene"](**medium)
    with pytest.raises(_FitStarted) as info:
        _fit([scene, fit_setup["target"], "--fit", *fit, "--out", str(fit_setup["tmp"] / "r.json")], capsys)
    init = info.value.args[0]
    for name, value in start.items():
        assert init[name] == pytest.approx(value, rel=1e-6)
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: scene.json: ")]
    assert len(notes) == len(start) and "is outside the fit's range" in notes[0] and "the search starts" in notes[0]


def test_fit_keeps_a_start_inside_the_range(fit_setup, capsys):
    with pytest.raises(_FitStarted) as info:
        _fit([fit_setup["scene"](), fit_setup["target"], "--out", str(fit_setup["tmp"] / "r.json")], capsys)
    assert info.value.args[0] == {"sigma_t": pytest.approx(0.5), "g": pytest.approx(0.6)}
    assert "note:" not in capsys.readouterr().out
