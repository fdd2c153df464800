"""Import Open3D, preloading libusb from the ``libusb-package`` wheel when the system lacks it.

Open3D's Linux wheel links against ``libusb-1.0.so.0`` (for RealSense support) although this
project never talks to USB devices. Bare Debian images do not ship that library; loading the copy
bundled by ``libusb-package`` with RTLD_GLOBAL before the import satisfies the dynamic linker, so
a plain ``pip install`` is enough.
"""

from __future__ import annotations

import ctypes
import importlib
from types import ModuleType

import numpy as np

_o3d: ModuleType | None = None


def open3d() -> ModuleType:
    """The ``open3d`` module, imported once."""
    global _o3d
    if _o3d is not None:
        return _o3d
    try:
        _o3d = importlib.import_module("open3d")
    except ImportError as exc:
        if "libusb" not in str(exc):
            raise
        try:
            import libusb_package
        except ImportError:
            raise ImportError(
                "open3d needs libusb-1.0.so.0: install the 'libusb-package' wheel "
                "(a dependency of this project) or the system package libusb-1.0-0"
            ) from exc
        path = libusb_package.get_library_path()
        if path is None:
            raise
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        _o3d = importlib.import_module("open3d")
    return _o3d


def point_cloud(points: np.ndarray):
    """An Open3D ``PointCloud`` of ``points [N, 3]`` (any frame), from a float64 copy: Open3D refuses a
    read-only array (a frame's cached points are read-only)."""
    o3d = open3d()
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, np.float64)))
