"""One exception tree for the package; each error also inherits the matching builtin."""
from __future__ import annotations


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
