"""The foreign fit suite (`data_synthetic/foreign/`, `fitting.suite`): targets rendered by Mitsuba 3.

Default (fast): the manifest is consistent with the files: every scene and target exists and loads, each target's
header records the case's truth and the renderer, the fitted parameters are valid names the scene has, and each
target is the scene camera's size. Slow (`pytest -m slow`, ~15-30 min on 2 cores): every case through
`python -m fitting.fit`, as `python -m fitting.suite` runs it: a case expected to pass within `suite.se_bound()` of its
standard errors (3.12 for 28 determined parameters: the family-wise bound at 5%, `suite.error_bound`) and within 2%
(sigma_t, intensity) / 0.02 (g, albedo) of the truth where the views determine the parameter, the
second waived only where the fit's own standard error shows the targets cannot give it (`suite.target_limited`); a
case expected to fail exits 1 with the message that the model does not explain the targets.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import jaxfog as jf
from fitting import suite
from fitting.fit import true_values
from fitting.params import SPECS, scene_values

MANIFEST = suite.load_manifest()
CASES = MANIFEST["cases"]
IDS = [c["name"] for c in CASES]


def test_manifest_lists_both_kinds_of_case():
    names = [c["name"] for c in CASES]
    assert len(names) == len(set(names))
    assert sum(c["expect"] == "fail" for c in CASES) >= 2
    assert sum(c["expect"] == "pass" for c in CASES) >= 5
    assert {len(c["views"]) for c in CASES} == {1, 2}
    files = {v["target"] for c in CASES for v in c["views"]}
    assert files == {t["file"] for t in MANIFEST["targets"]}, "targets section and cases disagree"


def test_manifest_is_the_generators():
    """manifest.json's cases are those of `make_foreign.CASES` (the script that rendered the targets)."""
    gen = suite._make_foreign()
    assert CASES == [json.loads(json.dumps(gen.manifest_case(c))) for c in gen.CASES]


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_manifest_case_consistent(case):
    assert case["expect"] in ("pass", "fail")
    assert set(case["init"]) == set(case["fit"])
    assert set(case["determined"]) <= set(case["fit"])
    assert case["expect"] == "fail" or case["determined"], "a case expected to pass must determine something"
    for n in case["fit"]:
        assert n in SPECS, n
        if case["expect"] == "pass":
            assert n in case["truth"], f"{n}: no truth"
    for v in case["views"]:
        for key in ("scene", "rendered_scene", "target"):
            assert os.path.exists(suite.REPO / v[key]), v[key]
        sf = jf.load_scene(suite.REPO / v["scene"])
        have = scene_values(sf.scene)
        assert all(n in have for n in case["fit"]), (case["fit"], sorted(have))
        img, meta = jf.read_exr(suite.REPO / v["target"])
        assert img.shape == (sf.scene.camera.height, sf.scene.camera.width, 3)
        assert np.all(np.isfinite(img)) and img.min() >= 0 and img.mean() > 0
        assert true_values(meta) == case["truth"], "header truth differs from the manifest"
        assert meta["renderer"].startswith("mitsuba 3"), meta.get("renderer")
        assert meta["jaxfog:scene_file"] == v["rendered_scene"]
        assert "jaxfog:spp" not in meta, "a Mitsuba target's noise is estimated from the image, not from jaxfog's spp"
        assert int(json.loads(meta["mitsuba:spp"])) >= 1024
        if v["rendered_scene"] == v["scene"]:  # same geometry: only the medium / light power differ
            assert case["expect"] == "pass" or "sigma_t[r]" in case["truth"]


def test_error_bound_is_family_wise():
    """Bonferroni over the suite's parameters: 1.96 for one, 3.12 for 28; the manifest's pass cases determine 28."""
    assert suite.error_bound(1) == pytest.approx(1.960, abs=1e-3)
    assert suite.error_bound(28) == pytest.approx(3.124, abs=1e-3)
    n = sum(len(c["determined"]) for c in CASES if c["expect"] == "pass")
    assert suite.se_bound() == pytest.approx(suite.error_bound(n))


def test_judge_applies_both_tolerances():
    case = {"name": "x", "description": "", "views": [{}], "fit": ["sigma_t", "g"], "init": {"sigma_t": 0.3, "g": 0},
            "truth": {"sigma_t": 0.5, "g": 0.6}, "determined": ["sigma_t", "g"], "expect": "pass"}
    res = {"params": {"sigma_t": 0.505, "g": 0.61}, "uncertainty": {"sigma_t": {"se": 0.004}, "g": {"se": 0.006}},
           "success": True, "messages": []}
    assert suite.judge(case, 0, res, 1.0)["ok"]
    res_far = dict(res, params={"sigma_t": 0.515, "g": 0.61})  # 3% off, 3.75 se: both violated
    assert not suite.judge(case, 0, res_far, 1.0)["ok"]
    res_loose = dict(res, params={"sigma_t": 0.515, "g": 0.61},
                     uncertainty={"sigma_t": {"se": 0.01}, "g": {"se": 0.006}})
    assert not suite.judge(case, 0, res_loose, 1.0)["ok"]  # within 2 se but beyond 2%
    assert not suite.judge(case, 1, res, 1.0)["ok"]  # a failed fit never passes
    # the tolerance is waived only where the targets' own noise puts it out of reach (2 se_target > tolerance), the
    # renders' share is the smaller, and the fit names what the views determine
    info = {"summary": ["sigma_t and g are well determined together along sigma_t - 0.45 g (standard error 0.005)"]}
    coarse = dict(res, params={"sigma_t": 0.505, "g": 0.64}, information=info,
                  uncertainty={"sigma_t": {"se": 0.004, "se_target": 0.003, "se_render": 0.001},
                               "g": {"se": 0.03, "se_target": 0.025, "se_render": 0.01}})
    assert suite.judge(case, 0, coarse, 1.0)["ok"]
    assert not suite.judge(case, 0, dict(coarse, params={"sigma_t": 0.505, "g": 0.67}), 1.0, bound=2.0)["ok"]
    assert suite.judge(case, 0, dict(coarse, params={"sigma_t": 0.505, "g": 0.67}), 1.0, bound=2.5)["ok"]
    assert not suite.judge(case, 0, dict(coarse, params={"sigma_t": 0.505, "g": 0.70}), 1.0)["ok"]  # 3.3 se
    renders = {"se": 0.03, "se_target": 0.012, "se_render": 0.025}  # more passes would reach the tolerance
    assert not suite.judge(case, 0, dict(coarse, uncertainty=dict(coarse["uncertainty"], g=renders)), 1.0)["ok"]
    assert not suite.judge(case, 0, dict(coarse, information={}), 1.0)["ok"]  # nothing named
    sharp = {"se": 0.03, "se_target": 0.009, "se_render": 0.005}  # the targets would allow 0.02
    assert not suite.judge(case, 0, dict(coarse, uncertainty=dict(coarse["uncertainty"], g=sharp)), 1.0)["ok"]
    # an honest "not pinned down" (exit 1) passes only where the targets limit the loose parameter and every
    # parameter is still within its bound; any other refusal never does
    loose = dict(coarse, success=False, messages=["not pinned down by these targets at this budget (standard error "
                                                  "above 0.1): ['g']; more spp, a larger budget or views"])
    assert suite.judge(case, 1, loose, 1.0)["ok"]
    assert not suite.judge(case, 1, dict(loose, uncertainty=dict(coarse["uncertainty"], g=sharp)), 1.0)["ok"]
    assert not suite.judge(case, 1, dict(loose, params={"sigma_t": 0.505, "g": 0.70}), 1.0)["ok"]
    edge = dict(loose, messages=loose["messages"] + ["parameters ran to the edge of their range: ['g']"])
    assert not suite.judge(case, 1, edge, 1.0)["ok"]
    assert not suite.judge(case, 2, loose, 1.0)["ok"]
    fail = dict(case, expect="fail", determined=[])
    msg = {"success": False, "messages": ["the model does not explain the target(s): residual is 9x"]}
    assert suite.judge(fail, 1, msg, 1.0)["ok"]
    assert not suite.judge(fail, 0, dict(res, success=True), 1.0)["ok"]
    assert not suite.judge(fail, 2, {}, 1.0)["ok"]  # an input error is not the clear refusal asked for


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_fit_suite_case(case, tmp_path):
    r = suite.run_case(case, tmp_path)
    detail = "\n".join(r["log_tail"])
    assert r["ok"], f"{case['name']}: {'; '.join(r['problems'])}\n{detail}"
    if case["expect"] == "pass":
        for row in r["rows"]:
            if row["determined"]:
                assert abs(row["error"]) <= suite.se_bound() * row["se"]
                assert abs(row["error"]) <= row["tolerance"] or row["target_limited"]
    else:
        assert r["exit"] == 1 and r["success"] is False
        assert any(suite.EXPLAIN_MESSAGE in m for m in r["messages"])
