"""The simulated world behind ``rig calibrate --sim``: a true rig near the design (``simulators.targets``) and
the calibration targets placed where an operator would put them.

Every quantity a calibration step estimates has a truth here (``truth_dict`` goes into the session manifest), so
the steps can be checked against it: camera intrinsics, distortion and pose, LED positions, directions and
gains, the polarizer extinction ratio, black-level pedestal and nonlinearity, the albedo scale, k.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from simulators.targets import (CalibrationTruth, CharucoBoardTarget, DarkTarget, DiffuseSphereTarget, MarkerPlate,
                                MarkerPlatesTarget, MirrorBallTarget, TargetWorld, TileTarget,
                                TranslucentSphereTarget, charuco_poses)

from rig.config import MATERIALS, RigConfig
from rig.acquire.geometry import RigGeometry, rig_geometry
from rig.calibration.layout import POSE_TARGET, calibration_geometry
from rig.config.calibration_settings import CalibrationSettings, aruco_dictionary

__all__ = ["SimulatedCalibrationWorld", "reference_material", "simulated_camera"]


def simulated_camera(sim: Any) -> Any:
    """The ``SimulatedCamera`` of a running ``rig.acquire.factory.SimulatedRig``."""
    from simulators.camera import SimulatedCamera

    cam = getattr(sim, "camera", None)
    if isinstance(cam, SimulatedCamera):
        return cam
    for c in getattr(sim, "_closers", []):
        if isinstance(c, SimulatedCamera):
            return c
    raise RuntimeError("the simulated rig has no SimulatedCamera (camera folder is not 'sim'?)")


def reference_material(config: RigConfig, settings: CalibrationSettings
                       ) -> tuple[str, tuple[float, ...], tuple[float, ...], float, float]:
    """(name, sigma_s' (3,), sigma_a (3,), eta, radius_mm) of the seed-k reference sphere."""
    s = settings.seed_k
    name = s.material or config.scene.material
    if s.sigma_s_prime_per_mm is not None and s.sigma_a_per_mm is not None:
        ssp, sa = tuple(s.sigma_s_prime_per_mm), tuple(s.sigma_a_per_mm)
        name = s.material or "custom"
    elif name in MATERIALS:
        ssp, sa = MATERIALS[name]
    elif not s.material:
        ssp, sa = config.scene.sigma_s_prime_per_mm, config.scene.sigma_a_per_mm
    else:
        raise ValueError(f"calibration.seed_k.material {name!r}: not in the material table; give "
                         "sigma_s_prime_per_mm and sigma_a_per_mm")
    eta = s.eta or config.estimation.eta
    radius = s.radius_mm or config.object.radius_mm
    return name, tuple(ssp), tuple(sa), float(eta), float(radius)


class SimulatedCalibrationWorld:
    """Truth + targets for one simulated rig. ``operate`` is the simulated operator. ``truth_kw`` go to
    ``CalibrationTruth.perturbed`` (defaults here: a 3 DN black pedestal, 1.5% nonlinearity)."""

    def __init__(self, config: RigConfig, settings: CalibrationSettings, *, seed: int | None = None,
                 **truth_kw: Any) -> None:
        self.config, self.settings = config, settings
        self.design = rig_geometry(config)
        self.seed = config.scene.seed if seed is None else int(seed)
        truth_kw.setdefault("black_offset_dn", 3.0)       # a pedestal the DNG does not declare
        truth_kw.setdefault("nonlinearity", 0.015)        # 1.5% compression at full scale
        self.truth = CalibrationTruth.perturbed(self.design.camera, self.design.led_positions_mm, seed=self.seed,
                                                **truth_kw)
        rng = np.random.default_rng(self.seed + 1009)
        true: dict[str, tuple[float, float, float]] = {}
        for name, xyz in calibration_geometry(config, settings).targets.items():
            if name.startswith("led_"):
                true[name] = tuple(self.truth.led_positions_mm[int(name[4:])].tolist())
            elif name == "key_led":
                true[name] = tuple(self.truth.led_positions_mm[self.design.key_led].tolist())
            elif POSE_TARGET.match(name):
                true[name] = tuple((np.asarray(xyz) + rng.normal(0.0, 1.5, 3)).tolist())
            else:
                true[name] = tuple(float(v) for v in xyz)
        self.truth.targets_mm = true
        self.offsets = {"mirror_ball": np.array([0.8, -1.1, 0.6]), "diffuse_sphere": np.array([-0.7, 0.9, -0.5]),
                        "tile": np.array([0.4, 0.2, -0.3])}
        self.world = TargetWorld(self.truth)
        self._targets: dict[str, Any] = {}

    # -- targets ------------------------------------------------------------------------------------------
    def target(self, name: str) -> Any:
        if name not in self._targets:
            self._targets[name] = self._make(name)
        return self._targets[name]

    def _make(self, name: str) -> Any:
        s, cam = self.settings, self.truth.camera.pinhole
        if name == "dark":
            return DarkTarget()
        if name == "charuco":
            b = s.board
            poses = charuco_poses(cam, b.squares_x * b.square_mm, b.squares_y * b.square_mm, b.views, seed=self.seed)
            return CharucoBoardTarget(b.squares_x, b.squares_y, b.square_mm, b.marker_mm,
                                      aruco_dictionary(b.dictionary), poses)
        if name == "pose_targets":
            p = s.pose_targets
            plates = []
            for tname, xyz in self.truth.targets_mm.items():
                m = POSE_TARGET.match(tname)
                if m:
                    normal = self.design.camera.C - np.asarray(xyz)
                    plates.append(MarkerPlate(int(m.group(1)), xyz, tuple(normal / np.linalg.norm(normal)),
                                              marker_mm=p.marker_mm, target_mm=p.target_mm, margin_mm=p.margin_mm))
            return MarkerPlatesTarget(plates, aruco_dictionary(p.dictionary))
        if name == "mirror_ball":
            b = s.mirror_ball
            return MirrorBallTarget(tuple(np.asarray(b.center_mm) + self.offsets[name]), b.radius_mm,
                                    extinction_ratio=self.truth.extinction_ratio,
                                    led_radius_mm=self.truth.led_radius_mm)
        if name == "diffuse_sphere":
            d = s.diffuse_sphere
            return DiffuseSphereTarget(tuple(np.asarray(d.center_mm) + self.offsets[name]), d.radius_mm, d.albedo)
        if name == "tile":
            r = s.radiometry
            return TileTarget(tuple(np.asarray(r.tile_center_mm) + self.offsets[name]), r.tile_normal, r.tile_mm,
                              r.reflectance)
        if name == "reference":
            from simulators.scene import SphereObject

            _, ssp, sa, eta, radius = reference_material(self.config, self.settings)
            sc = self.config.scene
            return TranslucentSphereTarget(SphereObject(sc.center_mm, radius, ssp, sa, eta,
                                                        tessellation=sc.tessellation))
        raise ValueError(f"unknown simulated calibration target {name!r}")

    def operate(self, op: dict[str, Any]) -> None:
        """The simulated operator: put ``op['target']`` in place (and a board in ``op['pose']``)."""
        if "target" in op:
            self.world.target = self.target(str(op["target"]))
        if "pose" in op:
            self.world.target.pose_index = int(op["pose"])

    # -- wiring ---------------------------------------------------------------------------------------------
    def attach(self, sim: Any) -> None:
        """Make the running simulated camera of ``sim`` render this world."""
        self.world.attach(simulated_camera(sim))

    def truth_geometry(self) -> RigGeometry:
        """What ``rig.acquire.factory.start_simulators`` builds the simulators from: true LEDs, camera and targets."""
        pos = self.truth.led_positions_mm
        return RigGeometry(pos, pos / np.linalg.norm(pos, axis=1, keepdims=True), self.truth.camera.pinhole,
                           self.design.key_led, dict(self.truth.targets_mm))

    def truth_dict(self) -> dict[str, Any]:
        d = self.truth.to_dict()
        d["simulated_calibration"] = True
        d["seed"] = self.seed
        d["placements_mm"] = {k: self.placement(k).tolist() for k in self.offsets}
        return d

    def placement(self, name: str) -> np.ndarray:
        """True centre (mm) of a placed target: mirror_ball, diffuse_sphere, tile."""
        return np.asarray(self.target(name).center_mm, float)
