"""ConstructAide: 4D BIM in construction-site photos."""

import os as _os

# pyrender picks its OpenGL platform at import time; headless EGL unless the user chose.
_os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

__version__ = "0.1.0"
