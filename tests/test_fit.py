"""The fit (fitting/): recovers known parameters on a small problem, reports failure on targets the model cannot
explain, and rejects bad arguments with clear errors."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

import jaxfog
from jaxfog._scene_io import scene_from_dict
from fitting.problem import make_view
from fitting.solver import FitConfig, fit_views
from fitting.fit import main as fit_main
from fitting.params import apply

# A small backlit scene: a point light in the fog in front of the camera, seen at scattering angles from 0 to ~60
# degrees (its halo pins g), and a lit floor (pins sigma_t through its extinction). 16 x 16 px, single scattering.
SCENE = {
    "name": "tiny_backlit",
    "camera": {"origin": [0, 1, 3], "target": [0, 1, 0], "up": [0, 1, 0], "fov": 50, "width": 16, "height": 16},
    "integrator": {"max_depth": 2, "spp": 16},
    "medium": {"sigma_t": 0.5, "albedo": 0.9, "g": 0.5},
    "shapes": [{"type": "rectangle", "center": [0, 0, 0], "edge_u": [8, 0, 0], "edge_v": [0, 0, -8],
                "bsdf": {"type": "diffuse", "reflectance": 0.5}}],
    "lights": [{"type": "point", "position": [0.0, 3.0, -0.5], "intensity": 20}],
}
TRUTH = {"sigma_t": 0.6, "g": 0.5}


def _scene():
    return scene_from_dict(json.loads(json.dumps(SCENE))).scene


@pytest.fixture(scope="module")
def target():
    # Target: "detached" estimator, seed never used by the fit, 16x the fit's spp.
    img = jaxfog.render(apply(_scene(), TRUTH), jax.random.key(991), 512, estimator="detached")
    return np.asarray(img)


def _fit(target, init, names=("sigma_t", "g"), scene=None, **kw):
    # 8 x 8 fit pixels (the target pooled 2 x 2); unit render 32 spp: approach passes 256, estimate passes 512 spp
    view = make_view(scene or _scene(), target, "tiny", downscale=2, target_spp=512)
    cfg = FitConfig(spp=32, seed=0, **kw)
    return fit_views([view], list(names), init, cfg, log=lambda *_: None)


CORNERS = [{"sigma_t": 0.05, "g": -0.8}, {"sigma_t": 0.05, "g": 0.9}, {"sigma_t": 3.0, "g": -0.8},
           {"sigma_t": 3.0, "g": 0.9}]
"""Four starts in the corners of the valid box: optical depth 0.15 to 9 across the scene, back- to forward
scattering."""


@pytest.fixture(scope="module")
def corner_fits(target):
    return [_fit(target, start) for start in CORNERS]


def test_fit_from_four_corners_gives_one_estimate(corner_fits):
    """A start is a hint: from every corner the fit finds the truth's basin, and the four estimates agree within
    their standard errors. Their target is common, so two estimates differ by the renders' noise alone, whose
    standard deviation is at most sqrt(se_i^2 + se_j^2): 3 of it (0.3% false alarms a pair)."""
    for res, start in zip(corner_fits, CORNERS):
        assert res.success, (start, res.messages)
    for n in TRUTH:
        for i in range(4):
            for j in range(i + 1, 4):
                a, b = corner_fits[i], corner_fits[j]
                tol = 3.0 * np.hypot(a.uncertainty[n]["se"], b.uncertainty[n]["se"])
                assert abs(a.params[n] - b.params[n]) <= tol, (n, CORNERS[i], CORNERS[j], a.params, b.params)


def test_fit_recovers_the_truth_within_its_standard_errors(corner_fits):
    """Each estimate within 3 of its standard errors (which include the target's own noise) of the truth, and the
    model check at the truth's basin reads near 1 (the limit is FitConfig.chi2_max)."""
    for res in corner_fits:
        for n, true in TRUTH.items():
            se = res.uncertainty[n]["se"]
            assert np.isfinite(se) and se > 0
            assert abs(res.params[n] - true) <= 3.0 * se, (n, res.params[n], true, se)
        assert res.chi2 < FitConfig.chi2_max


def test_fit_refuses_a_black_target(target):
    from fitting.params import FitError

    with pytest.raises(FitError, match="target is black"):
        _fit(np.zeros_like(target), {"sigma_t": 0.3, "g": 0.2})


def test_fit_says_the_model_does_not_explain_a_different_scene(target):
    """The light moved: no (sigma_t, g) of the searched box explains the image, and the message names the box and
    the best residual found there."""
    other = json.loads(json.dumps(SCENE))
    other["lights"][0]["position"] = [-1.0, 0.4, -0.5]
    img = jaxfog.render(apply(scene_from_dict(other).scene, TRUTH), jax.random.key(992), 512)
    res = _fit(np.asarray(img), {"sigma_t": 0.3, "g": 0.2})
    assert not res.success
    msg = next(m for m in res.messages if "does not explain" in m)
    assert "searched sigma_t" in msg and "distinct start" in msg and "the best residual is" in msg


def test_a_target_refused_for_one_firefly_is_fitted_without_it(target):
    """One pixel of the target holding 40% of its light (a single sample of huge weight, as another renderer draws
    next to a point light), noise from the image (no header spp): as it is, no point of the searched box explains
    it (the check reads about 1000x the noise) and the fit is refused; `fit_views` then fits the view without its
    firefly (`View.without_fireflies`), succeeds, names the pixel, and finds the truth within 3 standard errors."""
    t = target.copy()
    t[12, 3] += 0.4 / 0.6 * target.sum(axis=(0, 1))
    view = make_view(_scene(), t, "tiny", downscale=2)
    assert view.without_fireflies.fireflies == ((3, 12),)
    assert view.without_fireflies.firefly_share == pytest.approx(t[12, 3].sum() / t.sum(), rel=1e-5)  # about 40%
    cfg, init = FitConfig(spp=32, seed=0), {"sigma_t": 0.3, "g": 0.2}
    as_is = fit_views([view._replace(without_fireflies=None)], ["sigma_t", "g"], init, cfg, log=lambda *_: None)
    assert not as_is.success and any("does not explain" in m for m in as_is.messages), as_is.messages
    res = fit_views([view], ["sigma_t", "g"], init, cfg, log=lambda *_: None)
    assert res.success and res.fireflies == {"tiny": [[3, 12]]}, res.messages
    assert any("tiny 40%" in m and "no finite variance" in m for m in res.messages), res.messages
    assert res_ok(res)


def res_ok(res) -> bool:
    """Every parameter within 3 of its standard errors of the truth."""
    return all(abs(res.params[n] - true) <= 3.0 * res.uncertainty[n]["se"] for n, true in TRUTH.items())


def test_grey_model_on_a_chromatic_target_is_refused():
    """Extinction rising from red to blue: a grey sigma_t fits the channels' mean and leaves residuals of opposite
    sign in red and blue, which the per-channel check shows."""
    rgb = json.loads(json.dumps(SCENE))
    rgb["medium"]["sigma_t"] = [0.3, 0.6, 1.2]
    img = jaxfog.render(scene_from_dict(rgb).scene, jax.random.key(994), 512, estimator="detached")
    res = _fit(np.asarray(img), {"sigma_t": 0.5, "g": 0.5})
    assert not res.success
    assert any("does not explain" in m and "per channel" in m for m in res.messages), res.messages


# ------------------------------------------------------------------------------------------------- bad arguments
@pytest.fixture
def files(tmp_path, target):
    scene_path = tmp_path / "tiny.json"
    scene_path.write_text(json.dumps(SCENE))
    target_path = tmp_path / "t.exr"
    jaxfog.write_exr(str(target_path), target, {"jaxfog:spp": 512})
    small = tmp_path / "small.exr"
    jaxfog.write_exr(str(small), target[:8, :8], {})
    return scene_path, target_path, small, tmp_path


@pytest.mark.parametrize(
    "args, message",
    [
        (["--fit", "sigma_t", "gg"], "unknown parameter 'gg'"),
        (["--fit", "sigma_t", "--init", "g=1.5"], "g=1.5: valid range"),
        (["--fit", "sigma_t", "--init", "sigma_t"], "expects name=value"),
        (["--budget", "0"], "--budget must be > 0 seconds"),
        (["--solver", "lm"], "unrecognized arguments: --solver"),
        (["--candidates", "nope.json"], "--candidates"),
        (["--candidates", "view.exr"], "expects scene files"),
        (["--candidate-spp", "0"], "--candidate-spp must be >= 1"),
    ],
)
def test_bad_parameter_arguments(files, capsys, args, message):
    scene_path, target_path, _, tmp = files
    code = fit_main([str(scene_path), str(target_path), *args, "--out", str(tmp / "r.json")])
    assert code == 2
    assert message in capsys.readouterr().err


def test_target_of_wrong_size(files, capsys):
    scene_path, _, small, tmp = files
    code = fit_main([str(scene_path), str(small), "--out", str(tmp / "r.json")])
    assert code == 2
    assert "8x8 px but the scene's camera is 16x16 px" in capsys.readouterr().err


def test_missing_files(files, capsys):
    scene_path, target_path, _, tmp = files
    assert fit_main([str(scene_path), str(tmp / "nope.exr"), "--out", str(tmp / "r.json")]) == 2
    assert "not found" in capsys.readouterr().err
    assert fit_main([str(tmp / "nope.json"), str(target_path), "--out", str(tmp / "r.json")]) == 2
    assert "nope.json" in capsys.readouterr().err
    assert fit_main([str(target_path), "--out", str(tmp / "r.json")]) == 2
    assert "before any SCENE.json" in capsys.readouterr().err


def test_box_mean_averages_existing_neighbours_and_keeps_non_finite_values():
    from fitting.problem import box_mean

    x = np.arange(16.0).reshape(4, 4, 1)
    m = box_mean(x, 1)[..., 0]
    assert m[1, 1] == pytest.approx(np.mean(x[:3, :3]))          # interior: the 3 x 3 block
    assert m[0, 0] == pytest.approx(np.mean(x[:2, :2]))          # corner: the 4 pixels that exist
    assert m[0, 2] == pytest.approx(np.mean(x[:2, 1:4]))         # edge: 6 pixels
    np.testing.assert_array_equal(box_mean(x, 0), x)             # r = 0: unchanged
    y = x.copy()
    y[0, 0, 0] = np.inf
    my = box_mean(y, 1)[..., 0]
    assert np.isinf(my[0, 0])                                    # stays as it is
    assert my[1, 1] == pytest.approx(np.mean(np.delete(x[:3, :3].ravel(), 0)))  # and out of its neighbours' means


def test_rank_views_adds_a_candidate_s_information_in_relative_units():
    from fitting.information import rank_views

    names, values = ["sigma_t", "g"], {"sigma_t": 0.5, "g": 0.6}
    F = np.diag([1 / 0.005 ** 2, 1 / 0.05 ** 2])   # sigma_t 1% (relative), g 0.05: g is the worst determined
    ranking = rank_views(names, values, F, {"pins g": np.diag([0.0, 1 / 0.01 ** 2]),
                                            "pins sigma_t": np.diag([1 / 0.001 ** 2, 0.0]),
                                            "the same again": F})
    assert [r["view"] for r in ranking] == ["pins g", "the same again", "pins sigma_t"]
    best = ranking[0]
    assert best["worst_se_before"] == pytest.approx(0.05)
    assert best["se"]["g"] == pytest.approx(1 / np.sqrt(1 / 0.05 ** 2 + 1 / 0.01 ** 2))
    assert best["se"]["sigma_t"] == pytest.approx(0.01)          # 0.005 of 0.5
    assert ranking[1]["shrink"] == pytest.approx(np.sqrt(2.0))    # twice the information
    assert ranking[2]["shrink"] == pytest.approx(1.0) and ranking[2]["worst_combination"] == "g"


def test_candidate_fisher_is_symmetric_psd_and_scales_with_the_target_s_samples():
    from fitting.problem import candidate_fisher

    scene, key = _scene(), jax.random.key(5)
    F1 = candidate_fisher(scene, ["sigma_t", "g"], TRUTH, 16, 512, key)
    F2 = candidate_fisher(scene, ["sigma_t", "g"], TRUTH, 16, 1024, key)   # the same renders, twice the samples
    assert np.all(np.isfinite(F1)) and np.allclose(F1, F1.T)
    assert np.all(np.linalg.eigvalsh(F1) >= -1e-9 * np.abs(F1).max()) and np.trace(F1) > 0
    np.testing.assert_allclose(F2, 2.0 * F1, rtol=1e-6)
