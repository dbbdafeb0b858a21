"""Smoke runs of the benchmarks (--quick): they run to completion and print their figures.
The figures themselves are read by people, never asserted as timings."""
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(script, *args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), MPLBACKEND="Agg")
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)


def test_devices_benchmark_quick_prints_every_transport():
    proc = _run("devices.py", "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    text = json.dumps(data)
    for transport in ("serial/pty", "serial/TCP", "Modbus TCP"):
        assert transport in text


def test_single_image_benchmark_quick_prints_tables(tmp_path):
    out, png = tmp_path / "single_image.json", tmp_path / "single_image.png"
    proc = _run("single_image.py", "--json", str(out), "--png", str(png))
    assert proc.returncode == 0, proc.stderr
    assert "| direct |" in proc.stdout and "| pinv |" in proc.stdout and "TARGET Table-1" in proc.stdout
    data = json.loads(out.read_text())
    direct = data["table1"][0]
    assert direct["method"] == "direct" and direct["ok"] and direct["psnr_db"] > 20  # re-rendered image
    assert "table1_direct" in data["verdicts"]
    cost = {r["m"]: r for r in data["cost"]}  # cost against m, beside the literal dense method
    assert set(cost) == {1000, 3000}
    for r in cost.values():
        assert r["direct_s"] > 0 and r["pinv_s"] > 0 and r["dense_s"] > 0 and r["dense_note"] == "measured"
        assert abs(r["direct_sigma_s_prime"] / 2.19 - 1) < 0.02  # (observations from the forward model)
    assert "pinv_vs_dense" in cost[3000]["agreement"]
    if importlib.util.find_spec("matplotlib") is None:  # the optional extra "plots"
        assert "matplotlib is not installed" in proc.stdout
    else:
        assert png.stat().st_size > 0


def test_gradients_benchmark_quick_prints_throughput_and_memory(tmp_path):
    out = tmp_path / "gradients.json"
    proc = _run("gradients.py", "--json", str(out), "--megapixels", "0.3")      # the printout, not the figures
    assert proc.returncode == 0, proc.stderr
    assert "read floor" in proc.stdout and "pipeline / read floor" in proc.stdout and "/ frame set" in proc.stdout
    data = json.loads(out.read_text())
    assert data["pipeline_mps"] > 0 and min(data["floor_read_mps"]) > 0
    assert data["runs"]["pipeline"]["status"] == ["ok", "ok", "ok"]


def test_gradients_benchmark_relief_branch_runs(tmp_path):
    """The relief branch of rig estimate gradients (--relief-only: read floor + relief worker) at 0.15 MP."""
    out = tmp_path / "relief.json"
    proc = _run("gradients.py", "--json", str(out), "--megapixels", "0.15", "--relief-only")
    assert proc.returncode == 0, proc.stderr
    assert "relief branch peak process memory / frame set" in proc.stdout and "fitted window-channels" in proc.stdout
    relief = json.loads(out.read_text())["runs"]["relief"]
    assert relief["fitted_window_channels"] > 0 and relief["cpu_seconds_relief"] > 0
    assert sum(relief["window_status"]["ok"]) + sum(relief["window_status"]["weak"]) > 0


def test_monte_carlo_benchmark_quick_prints_figures():
    proc = _run("monte_carlo.py", "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    for key in ("point_light", "gradient_x"):
        assert data[key]["seconds"] > 0 and 0 < data[key]["rel_stderr_median"] < 1


def test_mc_single_image_benchmark_quick_prints_models_and_verdict():
    proc = _run("mc_single_image.py")
    assert proc.returncode == 0, proc.stderr
    assert "paths/s" in proc.stdout and "ACCEPTANCE (best model" in proc.stdout
    for model in ("mc-table", "dipole-better", "dipole-jensen"):
        assert f"| {model} |" in proc.stdout


def test_mc_gradients_benchmark_quick_prints_materials_and_models(tmp_path):
    out = tmp_path / "mc_gradients.json"
    proc = _run("mc_gradients.py", "--json", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "paths/s" in proc.stdout and "## D / D_true - 1 per material and channel" in proc.stdout
    models = ("dipole-jensen", "dipole-better", "mc-table", "dipole-jensen+reference")
    assert "| material | ch | D_true mm | " + " | ".join(models) + " |" in proc.stdout  # the per-model header
    for name in ("marble", "skin1"):
        for ch in "RGB":
            assert f"| {name} | {ch} |" in proc.stdout
        for model in models:
            assert f"| {model} | R |" in proc.stdout
    rows = json.loads(out.read_text())["rows"]
    assert len(rows) == 2 * 3 * len(models)
    assert all(r["status"].split()[0] in ("ok", "censored", "failed:") for r in rows)


def test_mc_vs_mitsuba_benchmark_quick_prints_table(tmp_path):
    """Needs the optional ``bench`` extra (Mitsuba 3); skipped without it (CI does not install it)."""
    import pytest
    if importlib.util.find_spec("mitsuba") is None:
        pytest.skip("mitsuba is not installed (the 'bench' extra)")
    out = tmp_path / "mc_vs_mitsuba.json"
    proc = _run("mc_vs_mitsuba.py", "--json", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "| scene | ch |" in proc.stdout and "image max = 0" in proc.stdout
    data = json.loads(out.read_text())
    assert [s["scene"] for s in data["scenes"]] == ["cube_point", "cube_point_eta1", "sphere_env",
                                                   "sphere_env_R", "relief_x"]
    for s in data["scenes"]:
        assert s["seconds_ours"] > 0 and s["seconds_mitsuba"] > 0 and s["compared_pixels"] > 0
        for ch in s["channels"]:
            assert ch["efficiency_ours"] > 0 and ch["efficiency_mitsuba"] > 0 and ch["mean_ratio"] > 0


def test_reference_speed_same_accuracy_rule_and_batch_makespans():
    """benchmarks/reference_speed.py's "same accuracy" (per channel: both within 10 %, or the new error at most the
    old one plus the new interval's half-width; no "ok" lost) and benchmarks/batch.py's modelled makespans (the
    greedy list schedule of rig.estimate.batch), without running either benchmark (both take minutes)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from reference_speed import same_accuracy

    old = {"err": [-0.015, 0.30], "status": ["ok", "weak"], "truth": [1.0, 1.0], "interval": [[0.9, 1.1], [0.5, 2.0]]}
    assert same_accuracy(old, {**old, "err": [-0.08, 0.50]}) == [True, True]          # within 10 %; 0.5 <= 0.3 + 0.75
    assert same_accuracy(old, {**old, "err": [0.12, 0.30]})[0] is False                  # 12 % > 1.5 % + 10 %
    assert same_accuracy(old, {**old, "status": ["weak", "weak"]})[0] is False           # an "ok" lost
    from rig.estimate.batch import list_schedule_makespan
    assert list_schedule_makespan([7.0, 12.3, 4.2, 3.7, 3.4, 3.7, 7.5, 16.0], 2) > list_schedule_makespan(
        [16.0, 7.0, 12.3, 4.2, 3.7, 3.4, 3.7, 7.5], 2)
