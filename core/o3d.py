"""Import open3d on machines without a system libusb.

open3d's wheel links ``libusb-1.0.so.0``; minimal machines lack it and ``import open3d`` fails.
The ``libusb-package`` wheel ships that library: loading it into the global symbol namespace
first satisfies the dynamic linker without a system install.
"""

from __future__ import annotations

import ctypes
import functools


@functools.cache
def open3d():
    """Return the open3d module, imported once after preloading the bundled libusb.

    The preload happens before the first import attempt: a failed ``import open3d`` leaves
    half-initialised modules behind, so retrying after a failure is not safe.
    """
    try:
        import libusb_package

        path = libusb_package.get_library_path()
        if path is not None:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # a system libusb may still be there; the import below says if not
    import open3d as o3d

    return o3d
