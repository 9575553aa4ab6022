"""The Cycles comparison's plumbing (benchmarks.bench_cycles): the pure scene translation `to_cycles` against
hand-computed values, the Cycles-side script's imports, and the exit code without a Cycles interpreter. None of the
default tests needs `bpy`; the end-to-end `--quick` run is marked slow and skipped where no interpreter with `bpy`
is found (`JAXFOG_CYCLES_PYTHON`, else this Python)."""

from __future__ import annotations

import ast
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench_cycles as bc

REPO = Path(__file__).resolve().parent.parent


def spot_fog_data(**changes) -> dict:
    """The validated spot_fog scene dict at 16 x 16 with `key=value` overrides."""
    from benchmarks.common import load

    return load("spot_fog", 16, [f"{k}={v}" for k, v in changes.items()]).data


def test_axes_map_y_up_to_z_up_as_a_rotation():
    """(x, y, z) -> (x, -z, y): jaxfog's up (+y) is Blender's +z, jaxfog's +z (toward the camera) Blender's -y, and
    the map is a proper rotation (determinant +1), so no image is mirrored."""
    m = np.array([bc.to_blender(e) for e in np.eye(3)]).T
    assert bc.to_blender([0, 1, 0]) == [0, 0, 1] and bc.to_blender([0, 0, 1]) == [0, -1, 0]
    assert np.allclose(m @ m.T, np.eye(3)) and np.linalg.det(m) == pytest.approx(1.0)


def test_camera_translation():
    """spot_fog's camera: at (0, 1, 4.5) jaxfog = (0, -4.5, 1) Blender, horizontal fov 40 degrees, looking along
    -Z (local) toward the target, right = world +x (jaxfog's +x is on the image's right)."""
    p = bc.to_cycles(spot_fog_data())
    m = np.array(p["camera"]["matrix"])
    assert p["camera"]["fov_x"] == pytest.approx(math.radians(40.0), rel=1e-12)
    assert (p["width"], p["height"]) == (16, 16)
    assert np.allclose(m[:3, 3], [0.0, -4.5, 1.0]) and np.allclose(m[3], [0, 0, 0, 1])
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
    forward = np.array([0.0, 4.5, -0.2]) / math.hypot(4.5, 0.2)  # target (0, 0, 0.8) - origin, in Blender axes
    assert np.allclose(-m[:3, 2], forward, atol=1e-12)
    assert np.allclose(m[:3, 0], [1.0, 0.0, 0.0], atol=1e-12)
    assert m[2, 1] > 0.99  # the camera's up is nearly world +z


def test_fog_coefficients():
    """sigma_t 0.5, albedo 0.9: Volume Scatter colour 1, density 0.45 (sigma_s = colour x density); Volume
    Absorption colour 0, density 0.05 (sigma_a = (1 - colour) x density); anisotropy g."""
    v = bc.to_cycles(spot_fog_data())["volume"]
    assert v["scatter_color"] == pytest.approx([1, 1, 1]) and v["scatter_density"] == pytest.approx(0.45)
    assert v["absorption_color"] == pytest.approx([0, 0, 0]) and v["absorption_density"] == pytest.approx(0.05)
    assert v["anisotropy"] == pytest.approx(0.6)


def test_chromatic_fog_coefficients_per_channel():
    """Per channel: colour x density = sigma_s for the scatter node, (1 - colour) x density = sigma_a for the
    absorption node (sigma_t (0.2, 0.5, 1.0), albedo (0.5, 0.9, 0.8) by hand)."""
    d = spot_fog_data()
    d["medium"] = {**d["medium"], "sigma_t": [0.2, 0.5, 1.0], "albedo": [0.5, 0.9, 0.8]}
    v = bc.to_cycles(d)["volume"]
    ss = np.array(v["scatter_color"]) * v["scatter_density"]
    sa = (1 - np.array(v["absorption_color"])) * v["absorption_density"]
    assert np.allclose(ss, [0.1, 0.45, 0.8]) and np.allclose(sa, [0.1, 0.05, 0.2])
    assert max(v["scatter_color"]) == pytest.approx(1.0) and min(v["absorption_color"]) == pytest.approx(0.0)


def test_spot_light_translation():
    """60 W/sr on the axis = 4 pi 60 = 753.98 W of Blender power (intensity P / 4 pi); spot_size = 2 x 20 degrees;
    at (0, 2.8, 0) = (0, 0, 2.8) Blender, shining along its local -Z = world -z (down)."""
    li = bc.to_cycles(spot_fog_data())["lights"][0]
    m = np.array(li["matrix"])
    assert li["type"] == "SPOT" and li["power"] == pytest.approx(753.982236861550, rel=1e-12)
    assert li["spot_size"] == pytest.approx(math.radians(40.0), rel=1e-12)
    assert li["spot_blend"] == pytest.approx(0.455060, abs=2e-6)
    assert np.allclose(m[:3, 3], [0, 0, 2.8]) and np.allclose(-m[:3, 2], [0, 0, -1])
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12) and np.linalg.det(m[:3, :3]) > 0


def test_spot_blend_gives_the_cones_equal_power():
    """The closed form of `spot_blend_matching` against quadrature of both falloffs over the cone: jaxfog's ramp
    linear in theta, Cycles' smoothstep in cos(theta) (edges 20/15, 30/20 and 10/9.5 degrees); a ramp too wide for
    Cycles' widest edge (blend 1) gets 1."""
    for c_deg, b_deg in ((20.0, 15.0), (30.0, 20.0), (10.0, 9.5)):
        blend = bc.spot_blend_matching(c_deg, b_deg)
        c, b = math.radians(c_deg), math.radians(b_deg)
        th = np.linspace(0.0, c, 400_001)
        ramp = np.clip((c - th) / (c - b), 0.0, 1.0)
        x = np.clip((np.cos(th) - math.cos(c)) / ((1 - math.cos(c)) * blend), 0.0, 1.0)
        smooth = x * x * (3 - 2 * x)
        powers = [np.trapezoid(f * np.sin(th), th) for f in (ramp, smooth)]
        assert powers[1] == pytest.approx(powers[0], rel=1e-6)
    assert bc.spot_blend_matching(20.0, 20.0) == 0.0 and bc.spot_blend_matching(30.0, 10.0) == 1.0
    with pytest.raises(ValueError, match="beam_width"):
        bc.spot_blend_matching(20.0, 25.0)


def test_bounce_limits_count_vertices_after_the_first():
    """max_depth 8 (segments) = 7 scattering vertices = 6 Cycles bounces; 2 (single scattering) = 0 bounces."""
    assert bc.cycles_bounces(8) == {"max": 6, "diffuse": 6, "glossy": 6, "transmission": 6, "volume": 6,
                                    "transparent": 8}
    assert bc.cycles_bounces(2)["max"] == 0
    with pytest.raises(ValueError, match="max_depth 1"):
        bc.cycles_bounces(1)


def test_shapes_translation():
    """The floor: a quad with the rectangle's corners, front normal cross(edge_u, edge_v) (jaxfog +y, Blender +z)
    from the vertex order; the sphere: centre (0.6, 0.5, -0.3) -> (0.6, 0.3, 0.5), radius and reflectances kept."""
    floor, sphere = bc.to_cycles(spot_fog_data())["shapes"]
    v = np.array(floor["vertices"])
    assert floor["type"] == "quad" and floor["reflectance"] == pytest.approx([0.5] * 3)
    assert np.allclose(np.sort(v[:, 0]), [-3, -3, 3, 3]) and np.allclose(np.sort(v[:, 1]), [-3, -3, 3, 3])
    assert np.allclose(v[:, 2], 0.0)
    n = np.cross(v[1] - v[0], v[3] - v[0])
    assert n[2] > 0 and np.allclose(n[:2], 0)
    assert sphere["center"] == pytest.approx([0.6, 0.3, 0.5]) and sphere["radius"] == 0.5
    assert sphere["reflectance"] == pytest.approx([0.7] * 3)


@pytest.mark.parametrize("path,value,match", [
    (("shapes", 1, "bsdf"), {"type": "mirror", "reflectance": 1.0}, "mirror"),
    (("lights", 0), {"type": "area", "center": [0, 2, 0], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1], "radiance": 1},
     "area"),
    (("medium", "phase"), {"type": "rayleigh"}, "rayleigh"),
])
def test_what_cycles_cannot_take_is_named(path, value, match):
    d = spot_fog_data()
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    with pytest.raises(ValueError, match=match):
        bc.to_cycles(d)


def test_cycles_script_imports_only_bpy_numpy_and_the_standard_library():
    """It runs under the Cycles interpreter, where neither jaxfog nor JAX is installed."""
    tree = ast.parse(bc.CYCLES_SCRIPT.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module.split(".")[0])
    allowed = {"bpy", "bmesh", "mathutils", "numpy"} | set(sys.stdlib_module_names)
    assert names and names <= allowed, names - allowed


def test_missing_cycles_interpreter_exits_2_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert bc.main(["--quick", "--out", str(out), "--cycles-python", str(tmp_path / "no_python")]) == 2
    assert "no Cycles interpreter" in capsys.readouterr().err and not out.exists()
    with pytest.raises(bc.CyclesMissing, match="cannot import bpy"):
        bc.check_cycles("/bin/false")  # runs, but is no Python with bpy


def _bpy_python() -> str | None:
    """An interpreter with bpy: `JAXFOG_CYCLES_PYTHON`, else this one; None if neither imports it."""
    python = bc.default_cycles_python()
    try:
        bc.check_cycles(python)
    except bc.CyclesMissing:
        return None
    return python


@pytest.mark.slow
def test_quick_run_end_to_end(tmp_path):
    """`--quick` (16 x 16): both references, the settings screen and the equal-error search, with the JSON."""
    python = _bpy_python()
    if python is None:
        pytest.skip("no interpreter with bpy (set JAXFOG_CYCLES_PYTHON)")
    import json

    assert bc.main(["--quick", "--out", str(tmp_path), "--cycles-python", python]) == 0
    r = json.loads((tmp_path / "cycles.json").read_text())
    assert r["screen"]["best"] in bc.QUICK.settings and len(r["cycles_target"]["rel_rmse_per_image"]) == bc.QUICK.draws
    assert r["equal_error"]["tries"] and r["blender_version"]
    m = r["means"]  # the same scene: the means agree to within their (large, 16 x 16) standard errors
    assert abs(m["jaxfog"] - m["cycles"]) < 5 * math.hypot(m["jaxfog_se"], m["cycles_se"])
    assert os.path.getsize(tmp_path / "cycles.json") > 0
