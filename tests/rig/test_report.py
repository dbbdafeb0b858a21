"""`rig report` on a simulated session: thumbnails, maps, R(d) with data points, parameters with intervals,
and the error-against-run-time table (the session carries the simulated truth)."""
import json
import re
import tomllib

import cv2
import pytest

from rig.acquire.capture import capture, simulated
from rig.cli import main
from rig.config import default_config_text, parse_config
from rig.acquire.plan import CaptureRequest
from rig.files.session import Session

SMALL = {"sphere": {"geodesic_frequency": 3},
         "camera": {"width_px": 32, "height_px": 32, "fx_px": 500.0, "key_exposure_s": 0.3},
         "scene": {"tessellation": 2}}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    data = tomllib.loads(default_config_text())
    for section, fields in SMALL.items():
        data[section].update(fields)
    cfg = simulated(parse_config(data, "small.toml"))
    out = capture(cfg, CaptureRequest(("gradients", "single-image")), sessions_dir=tmp_path_factory.mktemp("s"),
                  name="rep")
    assert out.result.status == "complete"
    return out.session


def test_html_report(session, capsys):
    assert main(["report", str(session.root), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    page = (session.root / "report" / "index.html").read_text()
    # every image the page shows exists and is a real PNG of the expected kind
    srcs = re.findall(r"<img src='([^']+)'", page)
    assert len(srcs) == 6 + 2 + 1                          # frames, albedo + diffuse normals, R(d)
    for src in srcs:
        img = cv2.imread(str(session.root / "report" / src))
        assert img is not None and img.shape[0] >= 32, src
    assert cv2.imread(str(session.root / "report" / "frame_0016_full_cross.png")).max() > 100   # lit, not black
    assert summary["profile_points"] and summary["status"] == "complete" and summary["verify"] == []
    assert set(summary["estimates"]) == {"gradients", "single-image"}
    # parameters with intervals, per estimator and channel
    params = [p for p in summary["parameters"] if p["parameter"].startswith("sigma_s'")]
    assert {(p["estimator"], p["channel"]) for p in params} == {(e, c) for e in ("gradients", "single-image")
                                                              for c in "RGB"}
    for p in params:
        lo, hi = p["interval"]
        assert lo <= p["value"] <= hi
    # simulated session: errors against the truth, with the estimators' run times
    errs = {r["quantity"]: r for r in summary["errors"]}
    assert errs["gradients sigma_s' [1/mm] G"]["truth"] == 2.62
    assert all(r["seconds"] > 0 for r in summary["errors"])
    assert "Error against run time" in page and "95% interval" in page


def test_markdown_report_without_rerunning_estimators(session, tmp_path):
    from rig.report import write_report
    before = {p.name: p.stat().st_mtime_ns for p in (session.root / "estimates").glob("*.json")}
    out = write_report(session.root, out_dir=tmp_path / "md", fmt="md", run_estimators=False)
    md = (tmp_path / "md" / "report.md").read_text()
    assert out["index"].endswith("report.md") and "## Parameters" in md and "![R(d)](profile.png)" in md
    assert all((tmp_path / "md" / name).is_file() for name in re.findall(r"\]\(([^)]+\.png)\)", md))
    assert {p.name: p.stat().st_mtime_ns for p in (session.root / "estimates").glob("*.json")} == before
    assert Session.open(session.root).verify() == []
