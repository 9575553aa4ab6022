"""Scene files: validation (every kind of bad input, with file, key path and range in the message), defaults,
overrides, the shipped scenes' numbers (shared/design/benchmark_scenes.md), and equality with the Python API."""

from __future__ import annotations

import copy
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog
from jaxfog import SceneError, load_scene
from jaxfog._scene_io import apply_overrides, scene_from_dict

from helpers import SCENES_DIR as SCENES, SPOT_FOG, spot_fog_dict


def load_modified(tmp_path, mutate, overrides=()):
    """Write spot_fog with `mutate(data)` applied to `bad.json` and load it."""
    data = spot_fog_dict()
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    return load_scene(path, overrides)


def assert_error(tmp_path, mutate, *expected, overrides=()):
    """Loading fails with a SceneError whose message starts with the file name and contains every `expected`."""
    with pytest.raises(SceneError) as info:
        load_modified(tmp_path, mutate, overrides)
    msg = str(info.value)
    assert msg.startswith("bad.json: "), msg
    for part in expected:
        assert part in msg, f"{part!r} not in {msg!r}"
    return msg


def setter(path: str, value):
    """A mutation setting a dotted path (list indices as integers) to `value`."""

    def mutate(data):
        *head, last = path.split(".")
        node = data
        for k in head:
            node = node[int(k)] if isinstance(node, list) else node[k]
        node[int(last) if isinstance(node, list) else last] = value

    return mutate


def deleter(path: str):
    def mutate(data):
        *head, last = path.split(".")
        node = data
        for k in head:
            node = node[int(k)] if isinstance(node, list) else node[k]
        del node[last]

    return mutate


# ------------------------------------------------------------------------------------------ one test per bad input
def test_unknown_key(tmp_path):
    assert_error(tmp_path, setter("camera.fvo", 40), "camera.fvo: unknown key",
                 "valid keys: origin, target, up, fov, width, height, near_clip")
    assert_error(tmp_path, setter("shapes.1.bsdf.roughness", 0.1), "shapes[1].bsdf.roughness: unknown key",
                 "valid keys: reflectance")
    assert_error(tmp_path, setter("colour", 1), "colour: unknown key", "valid keys: name, description, camera")


def test_wrong_type(tmp_path):
    assert_error(tmp_path, setter("camera.fov", "wide"), "camera.fov: got string 'wide'",
                 "expected a number in range (0, 180)")
    assert_error(tmp_path, setter("medium.sigma_t", "thick"), "medium.sigma_t: got string 'thick'",
                 "each in range [0, inf)")
    assert_error(tmp_path, setter("camera.width", True), "camera.width: got boolean true", "integer")
    assert_error(tmp_path, setter("shapes", {}), "shapes: got an object", "expected a list")
    assert_error(tmp_path, setter("camera", [1, 2]), "camera: got a list of 2", "expected an object with keys")


def test_wrong_vector_length(tmp_path):
    assert_error(tmp_path, setter("camera.origin", [0, 1]), "camera.origin: got a list of 2",
                 "expected a 3-vector")
    assert_error(tmp_path, setter("medium.albedo", [0.9, 0.9]), "medium.albedo: got a list of 2", "[r, g, b]")


def test_missing_required_field(tmp_path):
    assert_error(tmp_path, deleter("camera.fov"), "camera.fov: missing required field",
                 "expected a number in range (0, 180)")
    assert_error(tmp_path, deleter("camera"), "camera: missing required field", "expected an object with keys")
    assert_error(tmp_path, deleter("lights.0.type"), "lights[0].type: missing required field",
                 "valid types: 'point', 'spot', 'area'")
    assert_error(tmp_path, deleter("shapes.1.radius"), "shapes[1].radius: missing required field", "(0, inf)")


@pytest.mark.parametrize("g", [1, -1, 1.5])
def test_g_out_of_range(tmp_path, g):
    assert_error(tmp_path, setter("medium.g", g), f"medium.g: {g} is out of range", "valid range (-1, 1)")


def test_negative_sigma_t(tmp_path):
    assert_error(tmp_path, setter("medium.sigma_t", -0.1), "medium.sigma_t: -0.1 is out of range",
                 "valid range [0, inf)")
    assert_error(tmp_path, setter("medium.sigma_t", [0.5, -1, 0.5]), "medium.sigma_t[1]: -1 is out of range")
    load_modified(tmp_path, setter("medium.sigma_t", 0))  # no fog is a valid medium


@pytest.mark.parametrize("albedo", [-0.1, 1.2, [0.5, 0.5, 1.01]])
def test_albedo_out_of_range(tmp_path, albedo):
    assert_error(tmp_path, setter("medium.albedo", albedo), "medium.albedo", "is out of range",
                 "valid range [0, 1]")


def test_reflectance_out_of_range(tmp_path):
    assert_error(tmp_path, setter("shapes.0.bsdf.reflectance", 1.5), "shapes[0].bsdf.reflectance: 1.5",
                 "valid range [0, 1]")
    assert_error(tmp_path, setter("shapes.1.bsdf", {"type": "mirror", "reflectance": -0.2}),
                 "shapes[1].bsdf.reflectance: -0.2", "valid range [0, 1]")


def test_negative_intensity_and_radiance(tmp_path):
    assert_error(tmp_path, setter("lights.0.intensity", -60), "lights[0].intensity: -60 is out of range",
                 "valid range [0, inf)")
    point = {"type": "point", "position": [0, 2, 0], "intensity": [1, -1, 1]}
    assert_error(tmp_path, setter("lights.0", point), "lights[0].intensity[1]: -1", "[0, inf)")
    area = {"type": "area", "center": [0, 2, 0], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1], "radiance": -3}
    assert_error(tmp_path, setter("lights.0", area), "lights[0].radiance: -3 is out of range", "[0, inf)")


@pytest.mark.parametrize("path, shown", [
    ("lights.0.direction", "lights[0].direction"),
    ("shapes.0.edge_u", "shapes[0].edge_u"),
    ("shapes.0.edge_v", "shapes[0].edge_v"),
    ("camera.up", "camera.up"),
])
def test_zero_length_vector(tmp_path, path, shown):
    assert_error(tmp_path, setter(path, [0, 0, 0]), f"{shown}: [0, 0, 0] has zero length",
                 "of nonzero length")


def test_up_parallel_to_view(tmp_path):
    # view direction target - origin = (0, -0.2, -4.5); any multiple of it is parallel
    assert_error(tmp_path, setter("camera.up", [0, 0.4, 9]), "camera.up: [0, 0.4, 9] is parallel to the view",
                 "not parallel to target - origin")
    assert_error(tmp_path, setter("camera.target", [0, 1, 4.5]), "camera.target", "equals origin")


def test_edges_not_perpendicular(tmp_path):
    assert_error(tmp_path, setter("shapes.0.edge_v", [0.1, 0, -6]), "shapes[0].edge_v: [0.1, 0, -6]",
                 "not perpendicular to edge_u [6, 0, 0]", "relative tolerance 1e-6")
    area = {"type": "area", "center": [0, 2, 0], "edge_u": [1, 0, 0], "edge_v": [1, 0, 1], "radiance": 3}
    assert_error(tmp_path, setter("lights.0", area), "lights[0].edge_v", "not perpendicular")
    load_modified(tmp_path, setter("shapes.0.edge_v", [1e-8, 0, -6]))  # within the 1e-6 relative tolerance


@pytest.mark.parametrize("radius", [0, -0.5])
def test_non_positive_radius(tmp_path, radius):
    assert_error(tmp_path, setter("shapes.1.radius", radius), f"shapes[1].radius: {radius} is out of range",
                 "valid range (0, inf)")


@pytest.mark.parametrize("near_clip", [-0.01, float("inf")])
def test_near_clip_out_of_range(tmp_path, near_clip):
    assert_error(tmp_path, setter("camera.near_clip", near_clip), "camera.near_clip:", "[0, inf)")


def test_camera_near_clip_is_checked_in_python_too():
    with pytest.raises(ValueError, match="near_clip must be finite and >= 0"):
        jaxfog.Camera(origin=(0, 0, 0), target=(0, 0, -1), up=(0, 1, 0), fov=40, width=4, height=4, near_clip=-0.1)


@pytest.mark.parametrize("fov", [0, 180, 200, -10])
def test_fov_out_of_range(tmp_path, fov):
    assert_error(tmp_path, setter("camera.fov", fov), f"camera.fov: {fov} is out of range", "valid range (0, 180)")


@pytest.mark.parametrize("cutoff", [0, 90, 95])
def test_cutoff_out_of_range(tmp_path, cutoff):
    def mutate(data):
        data["lights"][0]["cutoff_angle"] = cutoff
        data["lights"][0]["beam_width"] = 0.5 * cutoff if cutoff else 1
    msg = assert_error(tmp_path, mutate, f"lights[0].cutoff_angle: {cutoff} is out of range", "valid range (0, 90)")
    assert "beam_width" not in msg


def test_beam_width_larger_than_cutoff(tmp_path):
    # the brief's example message, word for word (the file here is bad.json)
    msg = assert_error(tmp_path, setter("lights.0.beam_width", 25))
    assert msg == "bad.json: lights[0].beam_width: 25 is larger than cutoff_angle 20; valid range (0, cutoff_angle]"
    assert_error(tmp_path, setter("lights.0.beam_width", 0), "lights[0].beam_width: 0 is out of range",
                 "(0, cutoff_angle]")
    sf = load_modified(tmp_path, setter("lights.0.beam_width", 20))  # beam width = cutoff is allowed
    assert float(sf.scene.lights[0].beam_width) == 20


@pytest.mark.parametrize("path, value, shown", [
    ("camera.width", 0, "camera.width: 0 is out of range"),
    ("camera.height", -4, "camera.height: -4 is out of range"),
    ("camera.width", 12.5, "camera.width: got float 12.5"),
    ("integrator.spp", 0, "integrator.spp: 0 is out of range"),
    ("integrator.spp", 2.5, "integrator.spp: got float 2.5"),
    ("integrator.max_depth", 0, "integrator.max_depth: 0 is out of range"),
    ("integrator.max_depth", "8", "integrator.max_depth: got string '8'"),
])
def test_bad_integers(tmp_path, path, value, shown):
    assert_error(tmp_path, setter(path, value), shown, "[1, inf)")


@pytest.mark.parametrize("key", ["int_ior", "ext_ior"])
@pytest.mark.parametrize("ior", [0, -1.5])
def test_non_positive_ior(tmp_path, key, ior):
    glass = {"type": "glass", key: ior}
    assert_error(tmp_path, setter("shapes.1.bsdf", glass), f"shapes[1].bsdf.{key}: {ior} is out of range",
                 "valid range (0, inf)")


@pytest.mark.parametrize("path, value, shown, valid", [
    ("shapes.1.type", "cube", "shapes[1].type: 'cube' is not a known type", "valid types: 'sphere', 'rectangle'"),
    ("shapes.0.bsdf.type", "metal", "shapes[0].bsdf.type: 'metal' is not a known type",
     "valid types: 'diffuse', 'mirror', 'glass'"),
    ("lights.0.type", "laser", "lights[0].type: 'laser' is not a known type", "valid types: 'point', 'spot', 'area'"),
    ("lights.0.type", ["spot"], "lights[0].type: ['spot'] is not a known type", "valid types: 'point'"),
])
def test_unknown_type(tmp_path, path, value, shown, valid):
    assert_error(tmp_path, setter(path, value), shown, valid)


def test_non_finite_number(tmp_path):
    assert_error(tmp_path, setter("medium.sigma_t", float("nan")), "medium.sigma_t: nan is not finite")


@pytest.mark.parametrize("override, shown", [
    ("medium.sigma_t", "expected KEY.PATH=VALUE"),
    ("=0.3", "empty key"),
    ("medium..g=0.3", "empty key"),
])
def test_bad_override_syntax(override, shown):
    with pytest.raises(SceneError) as info:
        load_scene(SPOT_FOG, [override])
    msg = str(info.value)
    assert msg.startswith("spot_fog.json: override ") and repr(override) in msg and shown in msg, msg


@pytest.mark.parametrize("override, shown, valid", [
    ("medium.sigmat=1", "medium.sigmat: does not exist", "valid keys: sigma_t, albedo, g, phase, extent"),
    ("shapes.7.radius=1", "shapes[7]: does not exist (shapes has 2 entries)", "valid indices: 0..1"),
    ("lights.first.intensity=1", "'first' is not a list index", "valid indices: 0..0"),
    ("camera.width.3=1", "camera.width.3: does not exist (camera.width is int 128)", "existing key path"),
    ("foo.bar=1", "foo: does not exist", "valid keys: name, description, camera"),
])
def test_override_path_does_not_exist(override, shown, valid):
    with pytest.raises(SceneError) as info:
        load_scene(SPOT_FOG, [override])
    msg = str(info.value)
    assert msg.startswith(f"spot_fog.json: override {override!r}: "), msg
    assert shown in msg and valid in msg, msg


def test_missing_file_and_invalid_json(tmp_path):
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "nothere.json")
    bad = tmp_path / "broken.json"
    bad.write_text('{"camera": {"fov": 40,}}')
    with pytest.raises(SceneError, match=r"broken.json: invalid JSON at line 1, column"):
        load_scene(bad)


def test_scene_error_is_value_error():
    assert issubclass(SceneError, ValueError)


def test_validation_happens_before_anything_is_built(tmp_path, monkeypatch):
    """An invalid light (the last entry) must be found before the camera or any shape Module is made."""
    built = []
    for name in ("Camera", "Sphere", "Rectangle", "Diffuse", "SpotLight", "HomogeneousMedium"):
        monkeypatch.setattr(jaxfog, name, lambda *a, _n=name, **k: built.append(_n))
    assert_error(tmp_path, setter("lights.0.intensity", -1), "lights[0].intensity")
    assert built == []


# ------------------------------------------------------------------------------------------------------- defaults
def test_defaults(tmp_path):
    data = {
        "camera": {"origin": [0, 1, 4], "target": [0, 1, 0], "up": [0, 1, 0], "fov": 40, "width": 4, "height": 3},
        "shapes": [{"type": "sphere", "center": [0, 0, 0], "radius": 1, "bsdf": {"type": "mirror"}},
                   {"type": "sphere", "center": [3, 0, 0], "radius": 1, "bsdf": {"type": "glass"}}],
        "lights": [{"type": "spot", "position": [0, 3, 0], "direction": [0, -1, 0], "intensity": 1},
                   {"type": "spot", "position": [0, 3, 0], "direction": [0, -1, 0], "intensity": 1,
                    "cutoff_angle": 40}],
        "medium": {"sigma_t": 0.1, "albedo": 1, "g": 0},
    }
    path = tmp_path / "minimal.json"
    path.write_text(json.dumps(data))
    sf = load_scene(path)
    assert sf.name == "minimal" and sf.spp == 64 and sf.scene.max_depth == 8
    assert sf.data["integrator"] == {"max_depth": 8, "rr_depth": 5, "spp": 64} and sf.data["description"] == ""
    mirror, glass = sf.scene.shapes[0].bsdf, sf.scene.shapes[1].bsdf
    assert isinstance(mirror, jaxfog.Mirror) and np.all(np.asarray(mirror.reflectance) == 1)
    assert isinstance(glass, jaxfog.Glass) and float(glass.int_ior) == 1.5 and float(glass.ext_ior) == 1.0
    spot, wide = sf.scene.lights
    assert float(spot.cutoff_angle) == 20 and float(spot.beam_width) == 15
    assert float(wide.cutoff_angle) == 40 and float(wide.beam_width) == 30  # 0.75 * cutoff
    assert sf.scene.medium.extent == 1000.0
    assert sf.scene.medium.g.dtype == jnp.float32 and not sf.scene.medium.g.weak_type
    no_fog = copy.deepcopy(data)
    del no_fog["medium"]
    assert scene_from_dict(no_fog).scene.medium is None


# ------------------------------------------------------------------------------------------------------ overrides
def test_overrides_scalar_sets_all_channels_and_indices_work():
    sf = load_scene(SPOT_FOG, ["medium.sigma_t=0.8", "shapes.1.bsdf.reflectance=0.3", "lights.0.intensity=[1,2,3]",
                               "camera.width=32", "medium.g=-0.2"])
    np.testing.assert_array_equal(sf.scene.medium.sigma_t, np.full(3, 0.8, np.float32))
    np.testing.assert_array_equal(sf.scene.shapes[1].bsdf.reflectance, np.full(3, 0.3, np.float32))
    np.testing.assert_array_equal(sf.scene.lights[0].intensity, np.array([1, 2, 3], np.float32))
    assert sf.scene.camera.width == 32 and sf.scene.camera.height == 128
    assert float(sf.scene.medium.g) == pytest.approx(-0.2)
    assert sf.data["medium"]["sigma_t"] == 0.8  # data carries the overridden values


def test_overrides_order_and_absent_known_keys():
    data = spot_fog_dict()
    del data["integrator"]
    out = apply_overrides(data, ["integrator.spp=16", "medium.extent=50", "medium.g=0.1", "medium.g=0.2",
                                 "name=renamed"])
    assert out["integrator"] == {"spp": 16} and out["medium"]["extent"] == 50 and out["medium"]["g"] == 0.2
    assert out["name"] == "renamed"  # a bare word that is not JSON is a string
    assert "integrator" not in data and data["medium"]["g"] == 0.6  # the input is not modified
    sf = scene_from_dict(data, overrides=["integrator.spp=16"])
    assert sf.spp == 16 and sf.scene.max_depth == 8


def test_overrides_are_validated():
    with pytest.raises(SceneError, match=r"^spot_fog.json: medium.g: 1.5 is out of range; valid range \(-1, 1\)$"):
        load_scene(SPOT_FOG, ["medium.g=1.5"])
    with pytest.raises(SceneError, match=r"camera.width: got float 32.5"):
        load_scene(SPOT_FOG, ["camera.width=32.5"])


# ------------------------------------------------------------------------------------------- the shipped scenes
def _v(x):
    return np.asarray(x, dtype=np.float64)


def test_spot_fog_matches_benchmark_scenes_md():
    sf = load_scene(SPOT_FOG)
    s = sf.scene
    assert sf.name == "spot_fog" and sf.spp == 64 and s.max_depth == 8
    cam = s.camera
    np.testing.assert_array_equal(_v(cam.origin), [0, 1, 4.5])
    np.testing.assert_allclose(_v(cam.target), [0, 0.8, 0])
    np.testing.assert_array_equal(_v(cam.up), [0, 1, 0])
    assert float(cam.fov) == 40 and (cam.width, cam.height) == (128, 128)
    floor, sphere = s.shapes
    assert isinstance(floor, jaxfog.Rectangle) and isinstance(sphere, jaxfog.Sphere)
    np.testing.assert_array_equal(_v(floor.center), [0, 0, 0])
    np.testing.assert_array_equal(_v(floor.edge_u), [6, 0, 0])
    np.testing.assert_array_equal(_v(floor.edge_v), [0, 0, -6])
    np.testing.assert_array_equal(_v(floor.normal), [0, 1, 0])  # normal +y; x, z in [-3, 3]
    np.testing.assert_array_equal(_v(floor.bsdf.reflectance), [0.5] * 3)
    np.testing.assert_allclose(_v(sphere.center), [0.6, 0.5, -0.3], rtol=1e-7)
    assert float(sphere.radius) == 0.5
    np.testing.assert_allclose(_v(sphere.bsdf.reflectance), [0.7] * 3, rtol=1e-7)
    (spot,) = s.lights
    assert isinstance(spot, jaxfog.SpotLight)
    np.testing.assert_allclose(_v(spot.position), [0, 2.8, 0], rtol=1e-7)
    np.testing.assert_array_equal(_v(spot.direction), [0, -1, 0])
    np.testing.assert_array_equal(_v(spot.intensity), [60] * 3)
    assert float(spot.cutoff_angle) == 20 and float(spot.beam_width) == 15
    med = s.medium
    np.testing.assert_array_equal(_v(med.sigma_t), [0.5] * 3)
    np.testing.assert_allclose(_v(med.albedo), [0.9] * 3, rtol=1e-7)
    assert float(med.g) == pytest.approx(0.6)


@pytest.mark.parametrize("name, changes", [
    ("spot_fog_low", {"camera": {"origin": [0, 0.3, 1.8], "target": [0, 1.4, 0], "up": [0, 1, 0], "fov": 40,
                                 "width": 128, "height": 128}}),
    ("spot_fog_thin", {"medium": {"sigma_t": 0.05, "albedo": 0.9, "g": 0.6}}),
    ("spot_fog_dense", {"medium": {"sigma_t": 3, "albedo": 0.9, "g": 0.6}}),
])
def test_spot_fog_variants_differ_only_where_stated(name, changes):
    base, variant = spot_fog_dict(), json.loads((SCENES / f"{name}.json").read_text())
    assert variant["name"] == name
    for key in ("name", "description"):
        base.pop(key), variant.pop(key)
    assert variant == {**base, **changes}


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.json")), ids=lambda p: p.stem)
def test_every_shipped_scene_loads(path):
    sf = load_scene(path)
    assert sf.name == path.stem and sf.data["description"].strip()
    # the height-fog views (`height_fog_*`) and the phase-function fitting views (`*_fit_*`) are small on purpose
    # (32 x 32 targets, fitted at 8 x 8); the grid scene is 64 x 64 (a grid costs several times a homogeneous
    # medium per sample: docs/results/grid.md)
    size = 32 if path.stem.startswith("height_fog_") or "_fit_" in path.stem else 64 if path.stem == "grid_fog" else 128
    assert (sf.scene.camera.width, sf.scene.camera.height, sf.spp) == (size, size, 64)


def test_load_scene_builds_the_same_modules_as_the_python_api():
    f32 = jnp.float32
    by_hand = jaxfog.Scene(
        camera=jaxfog.Camera(origin=[0, 1, 4.5], target=[0, 0.8, 0], up=[0, 1, 0], fov=40, width=128, height=128),
        shapes=(
            jaxfog.Rectangle(center=[0, 0, 0], edge_u=[6, 0, 0], edge_v=[0, 0, -6], bsdf=jaxfog.Diffuse(0.5)),
            jaxfog.Sphere(center=[0.6, 0.5, -0.3], radius=0.5, bsdf=jaxfog.Diffuse(0.7)),
        ),
        lights=(jaxfog.SpotLight(position=[0, 2.8, 0], direction=[0, -1, 0], intensity=60, cutoff_angle=20,
                                 beam_width=15),),
        medium=jaxfog.HomogeneousMedium(sigma_t=0.5, albedo=0.9, phase=jaxfog.HenyeyGreenstein(f32(0.6))),
        max_depth=8,
    )
    loaded = load_scene(SPOT_FOG).scene
    assert jax.tree_util.tree_structure(loaded) == jax.tree_util.tree_structure(by_hand)  # incl. static fields
    for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(by_hand)):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
