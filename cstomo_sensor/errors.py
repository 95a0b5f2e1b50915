"""One exception tree for the package; each error also inherits the matching builtin. And what
installs each optional module (:func:`install_hint`), for the errors that name a missing one."""
from __future__ import annotations

import sys


class CstomoError(Exception):
    """Root of every error raised on purpose by cstomo_sensor."""


class ConfigError(CstomoError, ValueError):
    """A geometry, scene, parameter or file value is missing or out of range (names the field).

    Made by :meth:`bad_value`, it also carries the setting's ``key``, the ``value`` and what was
    ``expected``, so a caller (the node) can name the setting in its own words.
    """

    key: str | None = None
    value: object = None
    expected: str = ""

    @classmethod
    def bad_value(cls, key: str, value: object, expected: str) -> ConfigError:
        err = cls(f"{key}={value!r}: expected {expected}")
        err.key, err.value, err.expected = key, value, expected
        return err


class FrameError(CstomoError, ValueError):
    """A frame of voltages is malformed (wrong length, NaN/Inf, unparsable)."""


class NoUsableChannelsError(FrameError):
    """A frame's status flags exclude every measurement (all contacts failed, all saturated)."""


class ModelMismatchError(CstomoError, ValueError):
    """A cached or saved model was built for other inputs than the ones asked for."""


class MeshError(CstomoError, RuntimeError):
    """Meshing failed or produced a mesh that does not meet the quality bounds."""




def require_positive(name: str, value: object) -> None:
    """Raise :class:`ConfigError` naming ``name`` unless ``value`` is a positive finite number."""
    try:
        ok = 0.0 < float(value) < float("inf")
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ConfigError(f"{name}={value!r}: expected a positive finite number")


#: The optional modules the package imports only where it needs them: import name -> (pip package,
#: rosdep key or None). The one place that says what installs each (package.xml lists the keys,
#: README.md the pip line of the others).
OPTIONAL_MODULES: dict[str, tuple[str, str | None]] = {
    "skfem": ("scikit-fem", None),           # linear elasticity (model building)
    "pytetwild": ("pytetwild", None),        # meshing a geometry that has no shipped or cached mesh
    "pyvista": ("pyvista", "python3-pyvista-pip"),   # surfaces for meshing, pictures
    "vtk": ("vtk", "python3-pyvista-pip"),   # pyvista's own dependency
    "rosbags": ("rosbags", "python3-rosbags-pip"),   # replay, calibration from a bag
    "matplotlib": ("matplotlib", "python3-matplotlib"),  # pictures, benchmark figures
    "pyeit": ("pyeit", None),                # the benchmark's comparison only
}


def install_hint(module: str | None) -> str:
    """The command that installs the missing module ``module`` (an import name, e.g. ``skfem`` or
    ``skfem.helpers``) in the running interpreter's kind of install: a virtual environment gets
    its own pip; a system Python (a colcon install on a robot) the user's site, with the rosdep key
    when there is one."""
    top = (module or "").split(".")[0]
    pip_name, key = OPTIONAL_MODULES.get(top, (top, None))
    if not pip_name:
        return "install the Python package that provides it"
    if sys.prefix != sys.base_prefix:  # a virtual environment
        return f"install it with: {sys.executable} -m pip install {pip_name}"
    cmd = f"python3 -m pip install --user --break-system-packages {pip_name}"
    if key:
        return (f"install it with: rosdep install --from-paths src --ignore-src -y (key {key}; "
                f"PIP_BREAK_SYSTEM_PACKAGES=1 on Ubuntu 24.04), or {cmd}")
    return f"install it with: {cmd} (pip package {pip_name}; no rosdep key)"
