"""`jaxfog.scene_from_mitsuba_xml` and `jaxfog convert`: Mitsuba 3 XML scenes as jaxfog scene files.

The round trip: every shipped scene that `to_mitsuba` can express (and variants for what the shipped scenes lack:
bounded fog, a point and a directional light, Rayleigh scattering, an OBJ with smooth normals, no fog, `max_depth =
-1`) goes to a Mitsuba dict, to XML (`dict_to_xml` below: Mitsuba 3.9 has no `dict_to_xml`; where Mitsuba is
installed it loads that XML as the same scene as the dict), and back; the scene is the original one: the same
`to_mitsuba` dict, the same Modules to float32 rounding, the same image. Where Mitsuba is installed, its own parser
checks the importer's reading of transforms, fields of view, named indices of refraction and surface normals. Then one
test per kind of construct the importer refuses, each naming the element and its line, and the command line."""

from __future__ import annotations

import json
import os
import stat
import warnings
from pathlib import Path
from xml.sax.saxutils import quoteattr

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxfog as jf
from jaxfog._cli import main
from jaxfog._mitsuba import droplet_table, look_at_matrix
from jaxfog._mitsuba_xml import (IOR, MitsubaXmlError, MitsubaXmlWarning, _parse, _read_transform, _Reader,
                                 droplet_diameter, scene_from_mitsuba_xml)
from jaxfog._scene_io import scene_from_dict

REPO = Path(__file__).resolve().parent.parent
SCENES = sorted((REPO / "data_synthetic" / "scenes").glob("*.json"))
MATRIX = lambda m: m  # noqa: E731  (to_world as numpy matrices)


# ------------------------------------------------------------------------------------ a Mitsuba dict as XML
TAGS = {kind: tag for tag, kinds in {
    "integrator": "volpath volpathmis prbvolpath path", "sensor": "perspective", "film": "hdrfilm", "rfilter": "box",
    "sampler": "independent", "medium": "homogeneous heterogeneous", "volume": "gridvolume",
    "phase": "hg rayleigh blendphase tabphase isotropic", "shape": "rectangle sphere cube ply obj",
    "bsdf": "diffuse conductor dielectric null twosided", "emitter": "point spot area directional"}.items()
    for kind in kinds.split()}
"""The XML tag of each Mitsuba plugin type `to_mitsuba` writes."""


def _num(x) -> str:
    return repr(float(x))  # the shortest text that reads back as the same float64


def _xml_value(key, v, pad, out, folder):
    if isinstance(v, dict) and v.get("type") == "ref":
        out.append(f'{pad}<ref name={quoteattr(key)} id={quoteattr(v["id"])}/>')
    elif isinstance(v, dict) and v.get("type") == "rgb":
        out.append(f'{pad}<rgb name={quoteattr(key)} value="{", ".join(_num(x) for x in v["value"])}"/>')
    elif isinstance(v, dict):
        _xml_object(v, f"name={quoteattr(key)}", pad, out, folder)
    elif isinstance(v, bool):
        out.append(f'{pad}<boolean name={quoteattr(key)} value="{str(v).lower()}"/>')
    elif isinstance(v, (int, np.integer)):
        out.append(f'{pad}<integer name={quoteattr(key)} value="{int(v)}"/>')
    elif isinstance(v, float):
        out.append(f'{pad}<float name={quoteattr(key)} value="{_num(v)}"/>')
    elif isinstance(v, str):
        if key == "filename" and folder is not None:
            v = os.path.relpath(v, folder)  # relative to the XML file, as a user's scene has it
        out.append(f'{pad}<string name={quoteattr(key)} value={quoteattr(v)}/>')
    elif isinstance(v, np.ndarray) and v.shape == (4, 4):
        out += [f"{pad}<transform name={quoteattr(key)}>",
                f'{pad}    <matrix value="{" ".join(_num(x) for x in v.ravel())}"/>', f"{pad}</transform>"]
    elif isinstance(v, np.ndarray):  # a height-fog grid: named only (the importer refuses the medium before it)
        out.append(f'{pad}<string name="filename" value="{key}.vol"/>')
    elif isinstance(v, (list, tuple)) and len(v) == 3:
        tag = "vector" if key == "direction" else "point"
        out.append(f'{pad}<{tag} name={quoteattr(key)} value="{", ".join(_num(x) for x in v)}"/>')
    else:
        raise TypeError(f"no XML for {key!r}: {v!r}")


def _xml_object(d, ident, pad, out, folder):
    tag = TAGS[d["type"]]
    out.append(f'{pad}<{tag} type="{d["type"]}" {ident}>')
    for k, v in d.items():
        if k != "type":
            _xml_value(k, v, pad + "    ", out, folder)
    out.append(f"{pad}</{tag}>")


def dict_to_xml(d: dict, folder=None) -> str:
    """Mitsuba 3 XML of a `to_mitsuba` dict (numpy `to_world` matrices): top-level entries with their key as `id`,
    nested ones with it as `name`, in the dict's order; file names relative to `folder`."""
    out = ['<?xml version="1.0" encoding="utf-8"?>', '<scene version="3.0.0">']
    for k, v in d.items():
        if k != "type":
            _xml_object(v, f"id={quoteattr(k)}", "    ", out, folder)
    return "\n".join(out + ["</scene>"]) + "\n"


# ------------------------------------------------------------------------------------------ scenes to round-trip
def _load(path: Path) -> dict:
    data = json.loads(path.read_text())
    for sh in data.get("shapes", []):  # a dict has no folder: mesh files as absolute paths
        if sh["type"] == "mesh":
            sh["file"] = str(path.parent / sh["file"])
    return data


OCTAHEDRON = """# an octahedron with vertex normals
v 1 0 0\nv -1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nv 0 0 -1
vn 1 0 0\nvn -1 0 0\nvn 0 1 0\nvn 0 -1 0\nvn 0 0 1\nvn 0 0 -1
f 1//1 3//3 5//5\nf 3//3 2//2 5//5\nf 2//2 4//4 5//5\nf 4//4 1//1 5//5
f 3//3 1//1 6//6\nf 2//2 3//3 6//6\nf 4//4 2//2 6//6\nf 1//1 4//4 6//6
"""


def _variants(folder: Path) -> dict[str, dict]:
    """What the shipped scenes leave out, each made from one of them."""
    spot = _load(REPO / "data_synthetic" / "scenes" / "spot_fog.json")
    out = {}
    out["no_fog"] = {**spot, "medium": None}
    out["unbounded_depth"] = {**spot, "integrator": {"max_depth": -1, "rr_depth": 7, "spp": 16}}
    sun = _load(REPO / "data_synthetic" / "scenes" / "height_fog_above.json")
    out["sun_rayleigh"] = {**sun, "medium": {"sigma_t": [0.05, 0.1, 0.2], "albedo": [0.9, 0.8, 0.7],
                                             "phase": {"type": "rayleigh"}, "extent": 50}}
    point = _load(REPO / "data_synthetic" / "scenes" / "height_fog_point.json")
    out["point_light"] = {**point, "medium": {"sigma_t": 0.2, "albedo": 0.5, "g": -0.3}}
    glass = _load(REPO / "data_synthetic" / "scenes" / "mirror_glass.json")
    out["bounded_glass"] = {**glass, "medium": {"sigma_t": 0.8, "albedo": 0.9, "g": 0.5,
                                                "bounds": {"min": [-3, -0.5, -3], "max": [3, 3, 3]}}}
    (folder / "octahedron.obj").write_text(OCTAHEDRON)
    mesh = {"type": "mesh", "file": str(folder / "octahedron.obj"), "smooth": True,
            "bsdf": {"type": "diffuse", "reflectance": [0.6, 0.5, 0.4]},
            "to_world": {"scale": [0.4, 0.5, 0.3], "rotate": {"axis": [1, 1, 0], "angle": 30},
                         "translate": [-0.8, 0.5, 0.2]}}
    out["smooth_obj"] = {**spot, "shapes": spot["shapes"] + [mesh]}
    return out


def _shipped():
    """The shipped scenes `to_mitsuba` can express as a `homogeneous` medium (height fog is a `heterogeneous` one,
    which the importer refuses: tested below)."""
    return [p for p in SCENES if (json.loads(p.read_text()).get("medium") or {}).get("type", "homogeneous")
            == "homogeneous"]


ROUND_TRIP = [p.stem for p in _shipped()] + ["no_fog", "unbounded_depth", "sun_rayleigh", "point_light",
                                               "bounded_glass", "smooth_obj"]


def _original(name: str, folder: Path) -> dict:
    path = REPO / "data_synthetic" / "scenes" / f"{name}.json"
    return _load(path) if path.exists() else _variants(folder)[name]


def _write_xml(data: dict, folder: Path, name: str) -> Path:
    xml = folder / f"{name}.xml"
    xml.write_text(dict_to_xml(jf.to_mitsuba(data, transform=MATRIX, volume=lambda a: a), folder=folder))  # arrays even after another test set a Mitsuba variant
    return xml


def _assert_close(a, b, where="dict"):
    """Two `to_mitsuba` dicts equal, numbers to float32 rounding."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            _assert_close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, str):
        assert a == b, f"{where}: {a!r} != {b!r}"
    elif isinstance(a, (bool, int)) and not isinstance(a, float):
        assert a == b, f"{where}: {a!r} != {b!r}"
    else:
        np.testing.assert_allclose(np.asarray(b, np.float64), np.asarray(a, np.float64), rtol=2e-7, atol=1e-7,
                                   err_msg=where)


def _camera_matrix(cam):
    return look_at_matrix(cam.origin, cam.target, cam.up)


# ---------------------------------------------------------------------------------------------- round trip
@pytest.mark.parametrize("name", ROUND_TRIP)
def test_round_trip_through_mitsuba_xml(name, tmp_path):
    original = _original(name, tmp_path)
    xml = _write_xml(original, tmp_path, name)
    data = scene_from_mitsuba_xml(xml)
    assert data["name"] == name
    a, b = scene_from_dict(original), scene_from_dict(data)
    # the same Mitsuba scene (spp and seed are the sampler's)
    _assert_close(jf.to_mitsuba(a, transform=MATRIX), jf.to_mitsuba(b, transform=MATRIX))
    # the same jaxfog scene: the camera as the same look-at (the importer's target is origin + view direction) ...
    ca, cb = a.scene.camera, b.scene.camera
    np.testing.assert_allclose(_camera_matrix(cb), _camera_matrix(ca), atol=1e-6)
    assert (float(ca.fov), ca.width, ca.height) == pytest.approx((float(cb.fov), cb.width, cb.height))
    # ... and every other value to float32 rounding, with the same structure (kinds, depth, meshes' BVHs)
    sb = eqx.tree_at(lambda s: s.camera, b.scene, ca)
    assert jax.tree.structure(a.scene) == jax.tree.structure(sb)
    for x, y in zip(jax.tree.leaves(a.scene), jax.tree.leaves(sb)):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-6, atol=1e-7)
    assert (a.spp, a.scene.max_depth, a.scene.rr_depth) == (b.spp, b.scene.max_depth, b.scene.rr_depth)


def test_round_trip_renders_the_same_image(tmp_path):
    """The imported scene renders the original's image (the camera's float32 rounding aside)."""
    original = _original("spot_fog", tmp_path)
    original["camera"].update(width=6, height=5)
    original["integrator"] = {"max_depth": 2, "spp": 2}
    data = scene_from_mitsuba_xml(_write_xml(original, tmp_path, "tiny"))
    key = jax.random.key(3)
    a = np.asarray(jf.render(scene_from_dict(original).scene, key, 2))
    b = np.asarray(jf.render(scene_from_dict(data).scene, key, 2))
    assert np.all(np.isfinite(a)) and a.max() > 0
    np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6)


def test_droplet_tabphase_gives_back_its_diameter():
    for d in (8.0, 10.0, 0.37, 23.456):
        assert droplet_diameter(droplet_table(d, 4097)) == d
    table = droplet_table(10.0, 4097)
    table[100] *= 1.01  # not a droplet table any more
    assert droplet_diameter(table) is None
    assert droplet_diameter(np.full(4097, 1 / (4 * np.pi))) is None  # isotropic: no droplets


def test_height_fog_is_refused_as_heterogeneous(tmp_path):
    xml = _write_xml(_load(REPO / "data_synthetic" / "scenes" / "height_fog_point.json"), tmp_path, "height")
    line = next(i for i, t in enumerate(xml.read_text().splitlines(), 1) if 'type="heterogeneous"' in t)
    with pytest.raises(MitsubaXmlError, match=rf"height\.xml, line {line}: <medium type=\"heterogeneous\" id=\"fog\">:"
                                              r" the medium plugin 'heterogeneous' is not supported"):
        scene_from_mitsuba_xml(xml)


# --------------------------------------------------------------------------------------- a user's scene
USER = """<?xml version="1.0"?>
<scene version="3.0.0">
    <default name="spp" value="32"/>
    <default name="depth" value="6"/>
    <integrator type="volpathmis">
        <integer name="max_depth" value="$depth"/>
    </integrator>
    <medium type="homogeneous" id="haze">
        <rgb name="sigma_t" value="0.5, 0.25, 1"/>
        <float name="scale" value="0.4"/>
        <phase type="blendphase">
            <float name="weight" value="0.25"/>
            <phase type="hg"><float name="g" value="0.7"/></phase>
            <phase type="isotropic"/>
        </phase>
    </medium>
    <bsdf type="twosided" id="wall">
        <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf>
    </bsdf>
    <sensor type="perspective">
        <float name="fov" value="30"/>
        <string name="fov_axis" value="y"/>
        <transform name="to_world"><lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="20"/></film>
        <sampler type="stratified"><integer name="sample_count" value="$spp"/></sampler>
        <ref id="haze"/>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2"/><rotate x="1" angle="90"/><translate z="-1"/></transform>
        <ref id="wall"/>
        <ref name="exterior" id="haze"/>
    </shape>
    <shape type="sphere">
        <float name="radius" value="0.5"/>
        <transform name="to_world"><translate value="1 0.5 0"/></transform>
        <bsdf type="dielectric"><string name="int_ior" value="water"/></bsdf>
        <ref name="exterior" id="haze"/>
    </shape>
    <shape type="sphere">
        <point name="center" x="-1" y="0.5"/>
        <bsdf type="twosided"><bsdf type="conductor"/></bsdf>
    </shape>
    <shape type="obj">
        <string name="filename" value="meshes/octahedron.obj"/>
        <boolean name="face_normals" value="true"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><translate y="3"/></transform>
        <bsdf type="diffuse"><float name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="4, 3, 2"/></emitter>
    </shape>
    <emitter type="point">
        <transform name="to_world"><translate value="0.5, 2, 1"/></transform>
        <spectrum name="intensity" value="7"/>
    </emitter>
    <emitter type="directional"><vector name="direction" value="0, -1, -1"/></emitter>
    <emitter type="spot">
        <transform name="to_world"><lookat origin="0, 3, 0" target="0, 0, 0" up="1, 0, 0"/></transform>
        <float name="cutoff_angle" value="30"/>
    </emitter>
</scene>
"""


def _user_scene(tmp_path, text=USER) -> Path:
    (tmp_path / "meshes").mkdir(exist_ok=True)
    (tmp_path / "meshes" / "octahedron.obj").write_text(OCTAHEDRON)
    path = tmp_path / "user.xml"
    path.write_text(text)
    return path


@pytest.mark.filterwarnings("ignore:.*no rfilter:")  # tested below
def test_a_users_scene_with_defaults_refs_and_mitsubas_defaults(tmp_path):
    with pytest.warns(MitsubaXmlWarning, match=r"user\.xml, line 28: <shape type=\"rectangle\">: a twosided diffuse"):
        data = scene_from_mitsuba_xml(_user_scene(tmp_path))
    assert data["integrator"] == {"max_depth": 6, "spp": 32}
    cam = data["camera"]
    assert (cam["origin"], cam["target"], cam["up"]) == ([0, 1, 5], [0, 1, 0], [0, 1, 0])  # the lookat, verbatim
    assert cam["fov"] == pytest.approx(np.degrees(2 * np.arctan(np.tan(np.radians(15)) * 2)))  # fov_axis y, 2:1
    assert cam["near_clip"] == 0.01  # Mitsuba's default clip plane, which the converted camera keeps
    assert data["medium"] == {"sigma_t": [0.2, 0.1, 0.4], "albedo": 0.75,  # Mitsuba's default albedo
                              "phase": {"type": "two_term_hg", "g1": 0.7, "g2": 0.0, "w": 0.75}}
    wall, glass, mirror, mesh = data["shapes"]
    # scale 2, then +90 degrees about x (y -> z, z -> -y), then translate: a floor around z = -1 ...
    assert wall["center"] == [0, 0, -1]
    assert sorted(np.round(np.abs([wall["edge_u"], wall["edge_v"]]), 6).tolist()) == [[0, 0, 4], [4, 0, 0]]
    # ... whose normal (Mitsuba's +z -> -y) faced away from the camera: twosided, so it is turned toward it
    n = np.cross(wall["edge_u"], wall["edge_v"])
    assert n @ (np.array(cam["origin"]) - wall["center"]) > 0
    assert wall["bsdf"] == {"type": "diffuse", "reflectance": [0.2, 0.4, 0.6]}
    assert glass == {"type": "sphere", "center": [1, 0.5, 0], "radius": 0.5,
                     "bsdf": {"type": "glass", "int_ior": 1.333, "ext_ior": 1.000277}}
    assert mirror == {"type": "sphere", "center": [-1, 0.5, 0], "radius": 1, "bsdf": {"type": "mirror",
                                                                                       "reflectance": 1}}
    assert mesh == {"type": "mesh", "file": str(tmp_path / "meshes" / "octahedron.obj"), "smooth": False,
                    "bsdf": {"type": "diffuse", "reflectance": 0.5}}  # Mitsuba's default BSDF
    area, point, sun, spot = data["lights"]
    assert area["type"] == "area" and area["radiance"] == [4, 3, 2] and area["center"] == [0, 3, 0]
    np.testing.assert_allclose(np.cross(area["edge_u"], area["edge_v"]), [0, -4, 0], atol=1e-6)  # +z -> -y: down
    assert point == {"type": "point", "position": [0.5, 2, 1], "intensity": 7}
    assert sun == {"type": "directional", "direction": [0, -1, -1], "irradiance": 1}
    assert spot == {"type": "spot", "position": [0, 3, 0], "direction": [0, -1, 0], "intensity": 1,
                    "cutoff_angle": 30, "beam_width": 22.5}
    # parameters override the defaults, as mi.load_file(path, spp=...) does
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MitsubaXmlWarning)
        assert scene_from_mitsuba_xml(tmp_path / "user.xml", {"spp": 3})["integrator"]["spp"] == 3


@pytest.mark.filterwarnings("ignore::jaxfog._mitsuba_xml.MitsubaXmlWarning")  # sensors without a film
def test_a_cube_is_six_rectangles_facing_as_mitsubas(tmp_path):
    body = """<scene version="3.0.0">
    <sensor type="perspective"><transform name="to_world"><lookat origin="4, 3, 5" target="0, 0, 0" up="0, 1, 0"/>
    </transform></sensor>
    <shape type="cube"><transform name="to_world">{t}</transform></shape>
</scene>"""
    for t in ('<scale value="0.5, 1, 2"/><rotate y="1" angle="30"/><translate x="1"/>', '<scale x="-1"/>'):
        path = tmp_path / "cube.xml"
        path.write_text(body.format(t=t))
        data = scene_from_mitsuba_xml(path)
        center = np.array([1.0, 0, 0]) if "translate" in t else np.zeros(3)
        assert len(data["shapes"]) == 6 and data["integrator"] == {"max_depth": -1, "rr_depth": 5}
        for face in data["shapes"]:  # out; in under a mirror, as Mitsuba's (test_front_faces_are_mitsubas_normals)
            n = np.cross(face["edge_u"], face["edge_v"])
            assert (n @ (np.asarray(face["center"]) - center) > 0) == ("-1" not in t)


def test_what_differs_on_the_back_or_in_the_pixel_filter_is_a_warning(tmp_path):
    """A one-sided conductor (jaxfog's mirror is two-sided) and a two-sided diffuse (jaxfog's is one-sided) warn,
    except on spheres and for a twosided conductor; so does a film without a pixel filter."""
    path = tmp_path / "w.xml"
    path.write_text(BASE.replace("<!-- EXTRA -->", """<shape type="rectangle"><bsdf type="conductor"/></shape>
    <shape type="sphere"><bsdf type="conductor"/></shape>
    <shape type="rectangle"><bsdf type="twosided"><bsdf type="conductor"/></bsdf></shape>
    <shape type="sphere"><bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>"""))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = scene_from_mitsuba_xml(path)
    assert [str(w.message) for w in caught] == [
        "w.xml, line 13: <shape type=\"rectangle\">: a conductor (one-sided in Mitsuba) is read as jaxfog's mirror, "
        "which reflects on both sides: its back is black in Mitsuba, a mirror in jaxfog"]
    assert [s["bsdf"]["type"] for s in data["shapes"]] == ["diffuse", "mirror", "mirror", "mirror", "diffuse"]
    path.write_text(BASE.replace('<rfilter type="box"/>', ""))
    with pytest.warns(MitsubaXmlWarning, match=r"w\.xml, line 6: <film type=\"hdrfilm\">: no rfilter: Mitsuba's "
                                               r"default pixel filter is a gaussian"):
        scene_from_mitsuba_xml(path)


# ------------------------------------------------------------------------------------- Mitsuba's own reading
@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    return jf._mitsuba.import_mitsuba("scalar_rgb")


def test_mitsuba_loads_the_round_trip_xml_as_the_dict(mi, tmp_path):
    """The XML this file writes is the dict's scene in Mitsuba: the same image, sample for sample."""
    for name in ("spot_fog", "chromatic_haze", "droplet_fit_halo", "area_light", "mirror_glass", "mesh_fog"):
        original = _original(name, tmp_path)
        original["camera"].update(width=8, height=6)
        xml = _write_xml(original, tmp_path, name)
        d = jf.to_mitsuba(original, spp=4)
        a = np.asarray(mi.render(mi.load_dict(d), spp=4, seed=1))
        b = np.asarray(mi.render(mi.load_file(str(xml)), spp=4, seed=1))
        np.testing.assert_array_equal(b, a, err_msg=name)


def test_transforms_compose_as_in_mitsuba(mi, tmp_path):
    ops = ['<translate x="1" y="2" z="3"/><scale value="2, 3, 4"/>',
           '<scale value="2"/><rotate value="0, 1, 0" angle="30"/><translate value="1 2 3"/>',
           '<rotate x="2" angle="90"/>',  # Mitsuba does not normalise the axis
           '<matrix value="1 0 0 1  0 0 -1 2  0 1 0 3  0 0 0 1"/><rotate z="1" angle="-45"/>',
           '<matrix value="0 1 0  1 0 0  0 0 1"/><scale z="-1"/>',
           '<lookat origin="1, 2, 3" target="0, 0, 0" up="0, 1, 0"/><translate x="1"/>']
    text = "".join(f'<shape type="rectangle" id="s{i}"><transform name="to_world">{o}</transform></shape>'
                   for i, o in enumerate(ops))
    path = tmp_path / "t.xml"
    path.write_text(f'<scene version="3.0.0">{text}</scene>')
    params = mi.traverse(mi.load_file(str(path)))
    r = _Reader(str(path), {})
    for i, shape in enumerate(_parse(str(path))):
        ours = _read_transform(r, shape[0]).matrix
        theirs = np.asarray(params[f"s{i}.to_world"].matrix, np.float64)
        np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-6, err_msg=ops[i])


@pytest.mark.filterwarnings("ignore::jaxfog._mitsuba_xml.MitsubaXmlWarning")  # sensors without a film
@pytest.mark.parametrize("aspect", [(40, 20), (20, 40)])
def test_fields_of_view_as_mitsuba_converts_them(mi, tmp_path, aspect):
    w, h = aspect
    for spec in ('<float name="fov" value="35"/>', '<float name="fov" value="35"/><string name="fov_axis" value="y"/>',
                 '<float name="fov" value="35"/><string name="fov_axis" value="diagonal"/>',
                 '<float name="fov" value="35"/><string name="fov_axis" value="smaller"/>',
                 '<float name="fov" value="35"/><string name="fov_axis" value="larger"/>',
                 '<string name="focal_length" value="28mm"/>', ""):
        path = tmp_path / "fov.xml"
        path.write_text(f'<scene version="3.0.0"><sensor type="perspective" id="cam">{spec}<film type="hdrfilm">'
                        f'<integer name="width" value="{w}"/><integer name="height" value="{h}"/></film></sensor>'
                        '</scene>')
        want = mi.traverse(mi.load_file(str(path)))["cam.x_fov"]
        assert scene_from_mitsuba_xml(path)["camera"]["fov"] == pytest.approx(float(want), rel=1e-6), spec


def test_named_indices_of_refraction_are_mitsubas(mi, tmp_path):
    names = list(IOR)
    text = "".join(f'<shape type="sphere" id="s{i}"><bsdf type="dielectric"><string name="int_ior" value="{n}"/>'
                   '<string name="ext_ior" value="vacuum"/></bsdf></shape>' for i, n in enumerate(names))
    path = tmp_path / "ior.xml"
    path.write_text(f'<scene version="3.0.0">{text}</scene>')
    params = mi.traverse(mi.load_file(str(path)))
    for i, n in enumerate(names):
        assert IOR[n] == pytest.approx(float(params[f"s{i}.bsdf.eta"]), rel=1e-6), n
    assert IOR["bk7"] / IOR["air"] == pytest.approx(
        float(mi.traverse(mi.load_dict({"type": "dielectric"}))["eta"]), rel=1e-6)  # the defaults


@pytest.mark.filterwarnings("ignore::jaxfog._mitsuba_xml.MitsubaXmlWarning")  # sensors without a film
def test_front_faces_are_mitsubas_normals(mi, tmp_path):
    """Rectangles (mirrored, flipped) and a cube's faces: jaxfog's front normal is the normal Mitsuba's ray
    intersection reports."""
    shapes = ['<shape type="rectangle"><transform name="to_world"><scale value="2, 1, 1"/><rotate x="1" angle="60"/>'
              "</transform></shape>",
              '<shape type="rectangle"><transform name="to_world"><scale x="-1"/><rotate y="1" angle="20"/>'
              "</transform></shape>",
              '<shape type="rectangle"><boolean name="flip_normals" value="true"/><transform name="to_world">'
              '<rotate x="1" angle="-90"/></transform></shape>',
              '<shape type="cube"><transform name="to_world"><scale value="0.5, 1, 2"/><rotate value="0.6, 0.8, 0" '
              'angle="40"/></transform></shape>',
              '<shape type="cube"><transform name="to_world"><scale value="1, -1, 1"/></transform></shape>']
    sensor = ('<sensor type="perspective"><transform name="to_world"><lookat origin="7, 8, 9" target="0, 0, 0" '
              'up="0, 1, 0"/></transform></sensor>')
    for text in shapes:
        path = tmp_path / "n.xml"
        path.write_text(f'<scene version="3.0.0">{sensor}{text}</scene>')
        scene = mi.load_file(str(path))
        for face in scene_from_mitsuba_xml(path)["shapes"]:
            c, n = np.asarray(face["center"]), np.cross(face["edge_u"], face["edge_v"])
            n = n / np.linalg.norm(n)
            off = 0.1 * np.asarray(face["edge_u"]) + 0.05 * np.asarray(face["edge_v"])  # inside the face
            # a rectangle from either side; a cube's face (the cube around 0) from outside
            for side in (1.0, -1.0) if "rectangle" in text else (float(np.sign(n @ c)),):
                o = c + off + side * 10 * n
                si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*(-side * n))))
                assert bool(si.is_valid()), text
                np.testing.assert_allclose(np.asarray(si.n, np.float64), n, atol=1e-5, err_msg=text)


# ------------------------------------------------------------------------------------------- refused
BASE = """<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="4"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 1, 4.5" target="0, 0.8, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/><rfilter type="box"/>
        </film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"/>
    </shape>
    <!-- EXTRA -->
</scene>
"""
EXTRA_LINE = 13

FOG_SENSOR = [("</sensor>", '<medium type="homogeneous" id="fog"/></sensor>')]
REFUSED = {
    # kind: (extra XML at line 13 | replacements, line of the refused element, what the message must say)
    "unknown tag": ("<sphere/>", 13, r"<sphere>: unknown tag <sphere> in <scene>"),
    "include": ('<include filename="more.xml"/>', 13, r"<include> is not supported"),
    "shape plugin": ('<shape type="disk"/>', 13, r"the shape plugin 'disk' is not supported.*reads cube, obj, ply"),
    "bsdf plugin": ('<shape type="sphere"><bsdf type="roughdielectric"/></shape>', 13,
                    r"<bsdf type=\"roughdielectric\">: the bsdf plugin 'roughdielectric' is not supported"),
    "emitter plugin": ('<emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>', 13,
                       r"the emitter plugin 'envmap' is not supported"),
    "medium plugin": ('<medium type="heterogeneous" id="m"/>', 13, r"the medium plugin 'heterogeneous'"),
    "phase plugin": ('<medium type="homogeneous" id="m">\n<phase type="sggx"/></medium>', 14,
                     r"<phase type=\"sggx\">: the phase plugin 'sggx' is not supported"),
    "tabulated phase": ('<medium type="homogeneous" id="m"><phase type="tabphase"><string name="values" '
                        'value="1, 2, 3"/></phase></medium>', 13, r"jaxfog's droplet table"),
    "integrator plugin": ([('<integrator type="volpath">', '<integrator type="direct">')], 2,
                          r"the integrator plugin 'direct' is not supported"),
    "path integrator in fog": ([('<integrator type="volpath">', '<integrator type="path">')] + FOG_SENSOR, 2,
                               r"ignores media"),
    "no integrator in fog": ([('<integrator type="volpath"><integer name="max_depth" value="4"/></integrator>', "")]
                             + FOG_SENSOR, 1, r"Mitsuba's default when the scene has none"),
    "sensor plugin": ([('<sensor type="perspective">', '<sensor type="thinlens">')], 3,
                      r"the sensor plugin 'thinlens' is not supported"),
    "second sensor": ('<sensor type="perspective"/>', 13, r"a second sensor .*line 3"),
    "film plugin": ([('<film type="hdrfilm">', '<film type="specfilm">')], 6, r"the film plugin 'specfilm'"),
    "pixel filter": ([('<rfilter type="box"/>', '<rfilter type="gaussian"/>')], 6, r"the rfilter plugin 'gaussian'"),
    "texture": ('<shape type="sphere"><bsdf type="diffuse">\n<texture type="bitmap" name="reflectance">'
                '<string name="filename" value="wood.png"/></texture></bsdf></shape>', 14,
                r"a texture 'bitmap' for 'reflectance' of <bsdf type=\"diffuse\"> is not supported"),
    "spectrum by wavelengths": ('<emitter type="point"><spectrum name="intensity" value="400:1, 700:2"/></emitter>',
                                13, r"<spectrum name=\"intensity\">: a spectrum given by wavelengths"),
    "unknown parameter": ('<shape type="sphere"><bsdf type="dielectric">\n<float name="alpha" value="0.1"/></bsdf>'
                          '</shape>', 14, r"<float name=\"alpha\">: parameter 'alpha' of <bsdf type=\"dielectric\">"),
    "camera far clip plane": ([('<float name="fov" value="40"/>', '<float name="fov" value="40"/><float '
                                'name="far_clip" value="100"/>')], 3, r"far_clip below 10000"),
    "negative near clip plane": ([('<float name="fov" value="40"/>', '<float name="fov" value="40"/><float '
                                   'name="near_clip" value="-1"/>')], 3, r"near_clip must be >= 0"),
    "fov axis": ([('<float name="fov" value="40"/>', '<float name="fov" value="40"/><string name="fov_axis" '
                   'value="z"/>')], 3, r"fov_axis 'z' is not one of"),
    "scaled camera": ([('<lookat origin="0, 1, 4.5" target="0, 0.8, 0" up="0, 1, 0"/>', '<scale value="2"/>')], 3,
                      r"a rotation and a translation"),
    "hidden emitters": ([('<integer name="max_depth" value="4"/>', '<boolean name="hide_emitters" value="true"/>')],
                        2, r"hide_emitters"),
    "Fresnel conductor": ('<bsdf type="conductor" id="gold"><string name="material" value="Au"/></bsdf>', 13,
                          r"<bsdf type=\"conductor\" id=\"gold\">: a Fresnel conductor"),
    "twosided of two": ('<bsdf type="twosided" id="x"><bsdf type="diffuse"/><bsdf type="diffuse"/></bsdf>', 13,
                        r"a different BSDF on each side"),
    "parallelogram": ('<shape type="rectangle"><transform name="to_world"><matrix value="1 1 0 0  0 1 0 0  0 0 1 0  '
                      '0 0 0 1"/></transform></shape>', 13, r"parallelogram"),
    "ellipsoid": ('<shape type="sphere"><transform name="to_world"><scale x="2"/></transform></shape>', 13,
                  r"non-uniform scale"),
    "area emitter on a sphere": ('<shape type="sphere"><bsdf type="diffuse"><float name="reflectance" value="0"/>'
                                 '</bsdf><emitter type="area"/></shape>', 13, r"jaxfog's area lights are rectangles"),
    "area light that reflects": ('<shape type="rectangle"><emitter type="area"/></shape>', 13, r"a black BSDF"),
    "area emitter alone": ('<emitter type="area"/>', 13, r"an area emitter belongs inside"),
    "two media": ('<medium type="homogeneous" id="a"/><shape type="sphere"><ref name="exterior" id="a"/>\n'
                  '<medium type="homogeneous" name="interior"><float name="sigma_t" value="2"/></medium></shape>', 14,
                  r"a second medium \(the first is <medium type=\"homogeneous\" id=\"a\"> on line 13\)"),
    "fog in glass": ('<shape type="sphere"><bsdf type="dielectric"/><medium type="homogeneous" name="interior"/>'
                     '</shape>', 13, r"a medium inside a dielectric"),
    "fog sphere": ('<shape type="sphere"><bsdf type="null"/><medium type="homogeneous" name="interior"/></shape>', 13,
                   r"a shape with a null BSDF is read only as"),
    "medium nowhere": ('<shape type="sphere">\n<medium type="homogeneous" name="exterior"/></shape>', 14,
                       r"neither the sensor's"),
    "rotated fog box": ('<shape type="cube"><transform name="to_world"><rotate y="1" angle="30"/></transform>'
                        '<bsdf type="null"/><medium type="homogeneous" name="interior"/></shape>', 13,
                        r"an axis-aligned box"),
    "camera in the box, not in the fog": ('<shape type="cube"><transform name="to_world"><scale value="9"/></transform>'
                                          '<bsdf type="null"/><medium type="homogeneous" name="interior"/></shape>', 3,
                                          r"the camera is inside the fog's cube but the sensor has no medium"),
    "glass in fog without exterior": ([("<!-- EXTRA -->", '<shape type="sphere"><bsdf type="dielectric"/></shape>')]
                                      + FOG_SENSOR, 13, r"a dielectric in the fog without the fog as its exterior"),
    "unresolved parameter": ('<shape type="sphere"><float name="radius" value="$r"/></shape>', 13,
                             r"\$r in value=\"\$r\" has no value"),
    "unknown id": ('<shape type="sphere"><ref id="nothing"/></shape>', 13, r"no object with id 'nothing'"),
    "not XML": ('<shape type="sphere">', 14, r"not well-formed XML: mismatched tag"),
    "missing mesh": ('<shape type="obj"><string name="filename" value="missing.obj"/></shape>', 13,
                     r"missing\.obj: mesh file not found"),
    "mirrored mesh": ('<shape type="obj"><string name="filename" value="flat.obj"/><boolean name="face_normals" '
                      'value="true"/><transform name="to_world"><scale z="-1"/></transform></shape>', 13,
                      r"a mirroring to_world on a mesh"),
    "mesh without normals": ('<shape type="obj"><string name="filename" value="flat.obj"/></shape>', 13,
                             r"flat\.obj has no vertex normals and face_normals is false"),
    "old version": ([('version="3.0.0"', 'version="0.6.0"')], 1, r"a Mitsuba 0.x scene"),
    "out of range": ('<shape type="sphere">\n<bsdf type="diffuse"><float name="reflectance" value="1.5"/></bsdf>'
                     '</shape>', None, r"refused\.xml: as a jaxfog scene: shapes\[1\]\.bsdf\.reflectance: 1\.5 is out "
                                       r"of range; .*\(shapes\[1\] is <shape type=\"sphere\"> on line 13\)"),
}


@pytest.mark.parametrize("kind", list(REFUSED))
def test_unsupported_construct_is_refused_with_its_line(kind, tmp_path):
    extra, line, message = REFUSED[kind]
    text = BASE
    for old, new in ([("<!-- EXTRA -->", extra)] if isinstance(extra, str) else extra):
        assert old in text
        text = text.replace(old, new, 1)
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    path = tmp_path / "refused.xml"
    path.write_text(text)
    where = r"refused\.xml, line " + str(line) + r"(, column \d+)?: " if line is not None else ""
    with pytest.raises(MitsubaXmlError, match=where + ".*" + message) as info:
        scene_from_mitsuba_xml(path)
    assert "\n" not in str(info.value)
    assert isinstance(info.value, jf.SceneError)


def test_the_base_of_the_refusals_is_accepted(tmp_path):
    path = tmp_path / "base.xml"
    path.write_text(BASE)
    data = scene_from_mitsuba_xml(path)
    assert data["integrator"] == {"max_depth": 4} and len(data["shapes"]) == 1 and "medium" not in data
    assert BASE.splitlines()[EXTRA_LINE - 1].strip() == "<!-- EXTRA -->"


def test_a_near_clip_plane_is_read_and_written_back(tmp_path):
    """The sensor's `near_clip` becomes the camera's and `to_mitsuba` writes it back; a camera without one gets the
    exporter's tiny `NEAR_CLIP`, which reads back as none."""
    from jaxfog._mitsuba import NEAR_CLIP, to_mitsuba

    path = tmp_path / "clip.xml"
    path.write_text(BASE.replace('<float name="fov" value="40"/>',
                                 '<float name="fov" value="40"/><float name="near_clip" value="0.25"/>'))
    data = scene_from_mitsuba_xml(path)
    assert data["camera"]["near_clip"] == 0.25
    assert to_mitsuba(data)["sensor"]["near_clip"] == 0.25
    del data["camera"]["near_clip"]
    assert to_mitsuba(data)["sensor"]["near_clip"] == NEAR_CLIP


# ------------------------------------------------------------------------------------------ command line
def test_convert_writes_a_scene_file_that_loads(tmp_path, capsys):
    xml = _write_xml(_original("mesh_fog", tmp_path), tmp_path, "mesh_fog")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "scene.json"
    assert main(["convert", str(xml), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "wrote" in printed and str(out) in printed
    data = json.loads(out.read_text())
    mesh = data["shapes"][1]
    assert not os.path.isabs(mesh["file"])  # relative to the scene file's folder
    sf = jf.load_scene(out)
    orig = jf.load_scene(REPO / "data_synthetic" / "scenes" / "mesh_fog.json")
    _assert_close(jf.to_mitsuba(orig, transform=MATRIX), jf.to_mitsuba(sf, transform=MATRIX))
    assert [p.name for p in out_dir.iterdir()] == ["scene.json"]  # no temp file left


def test_convert_parameters_and_warnings(tmp_path, capsys):
    xml = _user_scene(tmp_path)
    out = tmp_path / "user.json"
    assert main(["convert", str(xml), "-o", str(out), "-D", "spp=5", "-D", "depth=3"]) == 0
    err = capsys.readouterr().err
    assert err.count("jaxfog: warning: ") == 2 and "twosided diffuse" in err and "no rfilter" in err
    assert json.loads(out.read_text())["integrator"] == {"max_depth": 3, "spp": 5}


def test_convert_refuses_with_one_line(tmp_path, capsys):
    xml = tmp_path / "bad.xml"
    xml.write_text(BASE.replace("<!-- EXTRA -->", '<shape type="disk"/>'))
    out = tmp_path / "bad.json"
    out.write_text("{}")
    assert main(["convert", str(xml), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxfog: error: bad.xml, line 13: <shape type=\"disk\">") and "\n" not in err
    assert out.read_text() == "{}"  # an existing file is kept when the conversion fails

    good = tmp_path / "good.xml"
    good.write_text(BASE)
    out.chmod(stat.S_IRUSR)
    assert main(["convert", str(good), "-o", str(out)]) == 1
    assert "read-only" in capsys.readouterr().err and out.read_text() == "{}"
    for argv, says in ((["convert", str(good), "-o", str(tmp_path / "x.exr")], "expected a .json file name"),
                       (["convert", str(tmp_path / "none.xml"), "-o", str(tmp_path / "n.json")], "not found")):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("jaxfog: error: ") and says in err and "\n" not in err, err
    assert main(["convert", str(good), "-o", str(tmp_path / "x.json"), "-D", "nothing"]) == 2  # a usage error
    assert "argument -D: expected NAME=VALUE, got 'nothing'" in capsys.readouterr().err
