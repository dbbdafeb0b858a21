"""Issue 15's acceptance rules on the scene zoo's CI subset (benchmarks/scene_zoo.py --quick).

Six scenes of the zoo (drawn with default_rng(15); benchmarks/zoo/scenes.py) chosen to cover the failure classes
of issue 15: a visible face the point light does not reach, an index-matched (eta = 1) cube, an environment map
with a sun lobe, a Monte Carlo frame with its fireflies, exact zeros (read noise clipped at 0), camera shot + read
noise; 48 x 48 px, 64-spp frames, written as scene files and estimated through the user path
(rig.files.scene_file.load_scene + estimate_scene) with every model; mc-table+reference at 32 spp, at most 4 renders.

Rules (benchmarks/zoo/rules.py), asserted per model over the (scene, channel) pairs:
- S90 (mc-table+reference only; the flat models' edge bias is documented in docs/model-error.md): sigma_s' within
  10 % in >= 90 % of the pairs;
- S-all: every pair within 10 %, or flagged (status not "ok", or failed) with a 95 % interval covering the truth;
- A-all: sigma_a within 50 %, or flagged with an interval covering the truth, in every pair;
- C90: the 95 % intervals cover the truth in >= 90 % of the (scene, channel, parameter) pairs;
- W0: no pair reported ok (sigma_s' or sigma_a) with sigma_s' more than 25 % off;
- E0: no Python warning and nothing written to stderr during the estimates.
These are the project's rule "never confident and wrong" and issue 15's acceptance, on scenes nobody tuned for;
this test was written before the estimator fixes of issue 15 and failed on the estimator it was written against
(the failing rules and by how much: the report of the zoo branch). S90 is a known failure on this subset (strict
xfail: it turns red the day it passes). ~1.5-2.5 min on 2 cores.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import scene_zoo  # noqa: E402
from zoo.frames import build_scene  # noqa: E402
from zoo.scenes import QUICK_CLASSES, draw_zoo, quick_subset, quick_variant  # noqa: E402

#: the module fixture renders and estimates the whole subset inside the first test that asks for it: ~4.5 min on
#: a clean 2-core CI machine, above the suite's 300 s per-test timeout on a loaded one
pytestmark = pytest.mark.timeout(900)

RULES = ("S90", "S-all", "A-all", "C90", "W0", "E0")
#: known failure, measured (issue 15's first acceptance line, reported blocked there): at the subset's noise level
#: (64-spp frames, 32-spp references, 48 x 48 px) sigma_s' comes within 10 % on 5 of the 8 pairs; the misses are the
#: sun and sky scenes, which the rules' other lines see flagged with covering intervals
S90_KNOWN = ("the CI subset's sun- and sky-lit scenes are information-limited at 64/32 spp: 3-5/8 pairs within 10 %, "
             "the misses flagged weak with covering intervals (docs/model-error.md, section 4)")
CASES = [pytest.param(m, r, marks=pytest.mark.xfail(strict=True, reason=S90_KNOWN)) if r == "S90" else (m, r)
         for m in scene_zoo.MODELS for r in RULES if r != "S90" or m == "mc-table+reference"]


@pytest.fixture(scope="module")
def zoo(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("zoo") / "quick.json"
    assert scene_zoo.main(["--quick", "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_quick_subset_covers_the_failure_classes(zoo: dict[str, Any]) -> None:
    scenes = zoo["scenes"]
    assert len(scenes) >= 6
    covered = set().union(*(s["classes"] for s in scenes))
    assert set(QUICK_CLASSES) <= covered, set(QUICK_CLASSES) - covered
    for s in scenes:
        folder = Path(s["folder"])
        assert (folder / "scene.toml").exists() and (folder / "mesh.ply").exists()
        meta = s["meta"]
        assert meta["frame_spp"] == 64 and meta["object_pixels"] > 100
        if "unlit" in s["classes"]:
            assert meta["unlit_faces"] > 0
        if "zeros" in s["classes"]:
            assert meta["zero_fraction"] > 0      # exact zeros on the object
        for r in s["results"]:
            assert r["model"] in scene_zoo.MODELS and len(r["rows"]) == len(meta["truth"]["sigma_a_per_mm"])
    # the cache: the same description finds the folder without rendering
    spec = quick_variant(quick_subset(draw_zoo())[0])
    folder, meta = build_scene(spec, Path(scenes[0]["folder"]).parent)
    assert meta["cached"] and str(folder) == scenes[0]["folder"]


@pytest.mark.parametrize(("model", "rule"), CASES)
def test_acceptance_rule(zoo: dict[str, Any], model: str, rule: str) -> None:
    verdict = zoo["acceptance"][model][rule]
    failing = {"S90": lambda row: not row["within_s"], "S-all": lambda row: not row["pass_s"],
               "A-all": lambda row: not row["pass_a"], "C90": lambda row: not (row["covers_s"] and row["covers_a"]),
               "W0": lambda row: row["confident_wrong"], "E0": lambda row: False}[rule]
    offenders = [f"{s['name']} ch{row['channel']}: sigma_s' {row['err_s']:+.1%} ({row['status_s']}, covers "
                 f"{row['covers_s']}), sigma_a {row['err_a']:+.1%} ({row['status_a']}, covers {row['covers_a']})"
                 for s in zoo["scenes"] for r in s["results"] if r["model"] == model for row in r["rows"]
                 if failing(row)]
    warned = [f"{s['name']}: {w}" for s in zoo["scenes"] for r in s["results"] if r["model"] == model
              for w in r["warnings"] + r["stderr_lines"] + ([r["exception"]] if r["exception"] else [])]
    assert verdict["pass"], f"{model} {rule}: {verdict['text']}; " + (
        f"warnings: {warned}" if rule == "E0" else f"pairs: {offenders}")
