"""Write a capture folder of Monte Carlo frames of a relief slab (issue 16): the cached input of
tests/rig/test_folder_diffusion.py (the relief mesh makes Monte Carlo ~1000x slower per path than a sphere, so the
frames are rendered once and stored; rerun this script to regenerate them; minutes on one core).

    NUMBA_NUM_THREADS=1 python tests/data/make_relief_capture.py OUT_FOLDER MATERIAL [N_PX PX_MM SPP RMS_SLOPE]

Scene: a thick slab (simulators.scene.BumpySlabObject, eta 1.3, reduced coefficients of science.md sec. 2) with a
random relief (wavelengths 1.5-6 mm, RMS slope RMS_SLOPE), 362 LEDs at 1 m (rig.acquire.geometry.led_layout) rendered as a
distant map, full + x + y + z in both polarizations (the parallel frames add the analytic GGX lobe), an
orthographic camera looking along +y, a 14-bit sensor's expected values (no noise: the Monte Carlo error is the
noise). The folder has no geometry (shape "unknown"); ``true_normals.npy`` (H, W, 3, rig frame) holds the truth.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

MATERIALS = {  # science.md sec. 2 (reduced sigma_s', sigma_a in 1/mm)
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
}
ETA = 1.3
GAIN, BLACK, WHITE, EXPOSURE = 4.5e7, 512, 16383, 0.02


def main(out: str, material: str, n_px: int = 64, px_mm: float = 0.2, spp: int = 128, rms_slope: float = 0.1) -> None:
    from estimation.camera import OrthographicCamera
    from estimation.gradients import LedRig
    from rig.estimate.reference.folder_reference import renderable_camera
    from rig.acquire.geometry import led_layout
    from rig.estimate.capture_folder.write import write_frames_and_leds
    from simulators.camera import SensorModel
    from simulators.mc_capture import MCSettings
    from simulators.scene import BumpySlabObject, render_gradient_capture

    folder = Path(out)
    ssp, sa = MATERIALS[material]
    pos, _ = led_layout(6, 1000.0, -60.0)
    inten = np.full((len(pos), 3), 1000.0)
    rig = LedRig.from_positions(pos, inten)
    patterns = {p: rig.pattern_values(p) for p in ("full", "x", "y", "z")}
    cam = renderable_camera(OrthographicCamera.looking_at(width_px=n_px, height_px=n_px, pixel_size_mm=px_mm,
                                                          direction=(0.0, 1.0, 0.0)))
    slab = BumpySlabObject((0.0, 0.0, 0.0), tuple(ssp), tuple(sa), ETA, extent_mm=n_px * px_mm + 22.0,
                           patch_mm=0.25, rms_slope=rms_slope, wavelengths_mm=(1.5, 6.0), n_waves=48, seed=0)
    sensor = SensorModel(gain_dn_per_unit=GAIN, black_level_dn=BLACK, white_level_dn=WHITE, read_noise_dn=2.0,
                         electrons_per_dn=1.5)
    t0 = time.perf_counter()
    cap = render_gradient_capture(slab, cam, pos, inten, patterns, polarizations=("cross", "parallel"),
                                  exposure_s=EXPOSURE, sensor=sensor, noise=False, render_mode="mc",
                                  mc=MCSettings(spp=spp, seed=0, relief_step_mm=px_mm))
    seconds = time.perf_counter() - t0
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    lines = ['format = "sssrig-capture"', "format_version = 1", f'name = "relief-{material}"',
             f'description = "Monte Carlo relief slab, {material}, {n_px} px of {px_mm} mm, {spp} spp, '
             f'RMS slope {rms_slope}, {seconds:.0f} s (tests/data/make_relief_capture.py)"', ""]
    lines += write_frames_and_leds(folder, cap.frames, EXPOSURE, np.hstack([pos, inten]))
    np.save(folder / "true_normals.npy", np.nan_to_num(cap.normals).astype(np.float32))
    lines += ["[camera]", 'model = "orthographic"', f"pixel_size_mm = {px_mm!r}",
              "look_direction = [0.0, 1.0, 0.0]", "", "[radiometry]", f"eta = {ETA}",
              f"value_per_radiance_per_s = {GAIN / (WHITE - BLACK)!r}", ""]
    (folder / "capture.toml").write_text("\n".join(lines))
    print(f"{folder}: {material}, {n_px} px of {px_mm} mm, {spp} spp, {seconds:.1f} s")


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], *(int(a[2]), float(a[3]), int(a[4]), float(a[5])) if len(a) > 2 else ())
