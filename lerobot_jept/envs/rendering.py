"""Offscreen OpenGL set-up for MuJoCo, shared by the dataset builders and the evaluation envs.

MuJoCo picks its GL backend from ``MUJOCO_GL`` when it is first imported. Without a display, the default
(glfw) fails deep inside an env constructor, so every entry point calls :func:`setup_offscreen_gl` before
importing a simulator: it selects EGL unless the user chose otherwise, and checks that the backend's shared
library can be loaded, failing with one sentence that names the Debian package to install. The simulators
themselves are extras of the package, imported through :func:`import_simulator` only when an env is built.
"""

import ctypes.util
import importlib
import os

# backend -> (shared library that must load, Debian packages that provide it)
GL_BACKENDS = {
    "egl": ("EGL", "libegl1 libegl-mesa0 libgl1-mesa-dri"),
    "osmesa": ("OSMesa", "libosmesa6"),
    "glfw": ("glfw", "libglfw3 (and a display)"),
}


class RendererUnavailableError(RuntimeError):
    """No usable offscreen OpenGL backend for MuJoCo."""


def setup_offscreen_gl(default: str = "egl") -> str:
    """Select the MuJoCo GL backend (``MUJOCO_GL``, default EGL) and check its library is installed.

    Also sets ``PYOPENGL_PLATFORM`` to match, as robosuite and PyOpenGL read it. Returns the backend name.
    """
    backend = os.environ.setdefault("MUJOCO_GL", default).lower()
    if backend not in GL_BACKENDS:
        raise RendererUnavailableError(
            f"MUJOCO_GL={backend!r} is not an offscreen backend MuJoCo supports on this system; "
            f"set MUJOCO_GL to one of {sorted(GL_BACKENDS)} (egl is the fastest headless choice)."
        )
    if backend in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    library, packages = GL_BACKENDS[backend]
    if ctypes.util.find_library(library) is None:
        other = "osmesa" if backend == "egl" else "egl"
        raise RendererUnavailableError(
            f"MUJOCO_GL={backend} needs the {library} library, which is not installed: run "
            f"`apt-get install {packages}`, or set MUJOCO_GL={other} with `apt-get install "
            f"{GL_BACKENDS[other][1]}`."
        )
    return backend


# How each simulator is installed next to LeRobot (robosuite 1.5.2's mink requirement needs numpy < 2).
INSTALL = {
    "metaworld": "pip install 'lerobot_policy_jept[metaworld]'",
    "robosuite": "pip install 'lerobot_policy_jept[robosuite]' && pip install --no-deps robosuite==1.5.2",
}


def import_simulator(module: str, extra: str):
    """Import ``module`` of a simulator, or fail naming the commands that install it."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name is None or e.name.split(".")[0] != module.split(".")[0]:
            raise
        raise ModuleNotFoundError(
            f"{module} is not installed; the {extra} envs and builders need it: {INSTALL[extra]}", name=e.name
        ) from e
