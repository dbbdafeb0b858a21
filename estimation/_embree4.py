"""Intel Embree 4 called directly through ``ctypes``: scene build from shared float32 / uint32 arrays and
16-ray packet queries (``rtcIntersect16``), for :class:`estimation.rays.RayEngine`'s ``"embree"`` backend.

Why not ``embreex``'s own classes: its ``TriangleMesh`` copies the vertices and faces into Embree's buffers
element by element through Python indexing (0.08-0.3 s for a 100k-face mesh on the shared 2-core machine: most
of the engine's build time, Embree's own BVH build being 0.04-0.08 s there; docs/visibility.md). Here Embree reads
our arrays in place (``rtcSetSharedGeometryBuffer``) and rays go in packets of 16 (``rtcIntersect16``), one
``ctypes`` call per packet (a call per ray would cost more than the ray). The Embree library is the one
``embreex`` ships (its wheel vendors ``libembree4``), so nothing new is installed; where it cannot be loaded or
fails a known-answer check (one ray against one triangle, :func:`_self_test`), :class:`estimation.rays.RayEngine`
falls back to ``embreex``'s classes.

Layouts and constants: Embree 4 API reference (``rtcore_ray.h``, ``rtcore_buffer.h``, ``rtcore_geometry.h``):
``RTCRay16`` is twelve 16-float/uint arrays (org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar, mask,
id, flags: 768 bytes), followed by ``RTCHit16`` (Ng_x, Ng_y, Ng_z, u, v, primID, geomID, instID[levels], and
instPrimID[levels] when built with instance arrays); only tfar and primID are read back, and each packet is given
a 1,536-byte slot, more than either variant of the hit record needs.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
from typing import Any

import numpy as np
import numpy.typing as npt

PACKET = 16
_SLOT_BYTES = 1536                    # one RTCRayHit16 (1,280 or 1,344 bytes) rounded up to a multiple of 64
# float/uint field indices in a packet (each field is PACKET lanes): RTCRay16 then RTCHit16
_ORG, _TNEAR, _DIR, _TIME, _TFAR, _MASK, _ID, _FLAGS, _PRIM, _GEOM = 0, 3, 4, 7, 8, 9, 10, 11, 17, 18
_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_BUFFER_TYPE_INDEX, _RTC_BUFFER_TYPE_VERTEX = 0, 1
_RTC_FORMAT_UINT3, _RTC_FORMAT_FLOAT3 = 0x5003, 0x9003
_INVALID = 0xFFFFFFFF

_lib: Any = None
_device: Any = None


def _library() -> Any:
    """The ``libembree4`` shared library vendored by ``embreex`` (or found on the system), with the argument
    types of the few functions used; None where there is none."""
    global _lib, _device
    if _lib is not None:
        return _lib or None
    _lib = False
    try:
        import embreex
    except ImportError:
        return None
    here = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    names = (glob.glob(os.path.join(here, "embreex.libs", "libembree4*"))
             + glob.glob(os.path.join(os.path.dirname(embreex.__file__), ".dylibs", "libembree4*")))
    found = ctypes.util.find_library("embree4")
    for name in names + ([found] if found else []):
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        p, u, i = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int
        sz = ctypes.c_size_t
        for fname, res, args in (
                ("rtcNewDevice", p, [ctypes.c_char_p]), ("rtcNewScene", p, [p]), ("rtcNewGeometry", p, [p, i]),
                ("rtcSetSharedGeometryBuffer", None, [p, i, u, i, p, sz, sz, sz]),
                ("rtcCommitGeometry", None, [p]), ("rtcAttachGeometry", u, [p, p]), ("rtcReleaseGeometry", None, [p]),
                ("rtcCommitScene", None, [p]), ("rtcReleaseScene", None, [p]), ("rtcGetDeviceError", i, [p]),
                ("rtcIntersect16", None, [p, p, p, p])):
            fn = getattr(lib, fname)
            fn.restype, fn.argtypes = res, args
        device = lib.rtcNewDevice(None)
        if not device:
            continue
        _lib, _device = lib, device
        try:
            ok = _self_test()
        except (OSError, ValueError):
            ok = False
        if ok:
            return lib
        _lib, _device = False, None
    return None


def _self_test() -> bool:
    """A ray down the z axis onto the triangle z = 2 of a one-triangle scene, a second one beside it, and 15
    padding lanes: face 0 at t = 3 (the hit record's layout as assumed), -1 for the miss."""
    scene = Embree4Scene(np.array([[-1.0, -1.0, 2.0], [3.0, -1.0, 2.0], [-1.0, 3.0, 2.0]]), np.array([[0, 1, 2]]))
    prim, tfar = scene.intersect(np.array([[0.0, 0.0, 5.0], [9.0, 9.0, 5.0]]), np.array([[0.0, 0.0, -1.0]] * 2))
    return bool(prim[0] == 0 and prim[1] == -1 and abs(float(tfar[0]) - 3.0) < 1e-5 and np.isinf(tfar[1]))


class Embree4Scene:
    """A static Embree scene of one triangle mesh: ``vertices`` (V, 3) and ``faces`` (F, 3) in Embree's float32
    coordinates (already shifted and scaled by the caller). Raises OSError where the library is missing or the
    build fails."""

    def __init__(self, vertices: npt.ArrayLike, faces: npt.ArrayLike) -> None:
        lib = _library()
        if lib is None:
            raise OSError("libembree4 not found")
        v = np.zeros((len(vertices) + 1, 4), np.float32)       # 16-byte stride; one spare row for SIMD reads
        v[:-1, :3] = vertices
        f = np.ascontiguousarray(faces, dtype=np.uint32)
        self._v, self._f = v, f                                 # Embree reads these in place: keep them alive
        self._lib = lib
        self._scene = lib.rtcNewScene(_device)
        geom = lib.rtcNewGeometry(_device, _RTC_GEOMETRY_TYPE_TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, v.ctypes.data, 0, 16,
                                       len(v) - 1)
        lib.rtcSetSharedGeometryBuffer(geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT3, f.ctypes.data, 0, 12,
                                       len(f))
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self._scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self._scene)
        err = lib.rtcGetDeviceError(_device)
        if err:
            raise OSError(f"Embree error {err} building the scene")

    def __del__(self) -> None:
        if getattr(self, "_scene", None):
            self._lib.rtcReleaseScene(self._scene)
            self._scene = None

    def intersect(self, origins: npt.NDArray[np.floating], dirs: npt.NDArray[np.floating]
                  ) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
        """First hit of each ray (N, 3) from t = 0, in packets of 16: primitive index (N,) int32 (-1: miss) and
        tfar (N,) float32 in the scene's units along ``dirs`` (inf for a miss)."""
        n = len(origins)
        n_pk = -(-n // PACKET)
        buf = np.empty(n_pk * _SLOT_BYTES + 64, np.uint8)
        start = (-buf.ctypes.data) % 64                          # Embree wants 64-byte aligned packets
        slots = buf[start:start + n_pk * _SLOT_BYTES].reshape(n_pk, _SLOT_BYTES)
        fl = slots.view(np.float32).reshape(n_pk, -1, PACKET)    # (packet, field, lane)
        u32 = slots.view(np.uint32).reshape(n_pk, -1, PACKET)
        lanes = np.zeros((3, n_pk * PACKET), np.float32)
        for first, src, pad in ((_ORG, origins, 0.0), (_DIR, dirs, 1.0)):   # padding lanes: any finite ray
            lanes[:, n:] = pad
            lanes[:, :n] = src.T
            fl[:, first:first + 3] = lanes.reshape(3, n_pk, PACKET).transpose(1, 0, 2)
        fl[:, _TNEAR] = 0.0
        fl[:, _TIME] = 0.0
        fl[:, _TFAR] = np.inf
        u32[:, _MASK] = _INVALID                                 # every ray sees every geometry
        u32[:, _ID] = 0
        u32[:, _FLAGS] = 0
        u32[:, _PRIM:_GEOM + 1] = _INVALID
        valid = np.full(PACKET + 16, -1, np.int32)               # all lanes valid, 64-byte aligned
        vptr = valid.ctypes.data + (-valid.ctypes.data) % 64
        fn, scene, base = self._lib.rtcIntersect16, self._scene, slots.ctypes.data
        for k in range(n_pk):
            fn(vptr, scene, base + k * _SLOT_BYTES, None)
        prim = u32[:, _PRIM].reshape(-1)[:n].view(np.int32)
        return prim.copy(), fl[:, _TFAR].reshape(-1)[:n].copy()
