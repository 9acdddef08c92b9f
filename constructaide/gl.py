"""Headless OpenGL helpers shared by every module that renders with pyrender (EGL).

pyrender's EGL platform calls ``eglTerminate`` when a renderer is deleted. EGL displays are
per process, so that kills every other live context in the process (another renderer, the
render node's raster context). :func:`patch_pyrender_egl` makes ``delete`` destroy only the
renderer's own context; the display stays initialised until the process exits.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

_PATCHED = False


def patch_pyrender_egl() -> None:
    """Idempotent: make pyrender's EGL ``delete_context`` leave the shared display alone."""
    global _PATCHED
    if _PATCHED:
        return
    from pyrender.platforms import egl

    def delete_context(self: egl.EGLPlatform) -> None:
        from OpenGL.EGL import eglDestroyContext

        if self._egl_display is not None and self._egl_context is not None:
            eglDestroyContext(self._egl_display, self._egl_context)
        self._egl_context = None
        self._egl_display = None

    egl.EGLPlatform.delete_context = delete_context  # type: ignore[method-assign]
    _PATCHED = True


def offscreen_renderer(width_px: int, height_px: int):  # noqa: ANN201 - pyrender type, imported lazily
    """A pyrender OffscreenRenderer whose deletion does not break other EGL contexts."""
    patch_pyrender_egl()
    import pyrender

    return pyrender.OffscreenRenderer(width_px, height_px)
