"""One exception tree for the package; each error also inherits the matching builtin."""


class CstomoError(Exception):
    """Root of every error raised on purpose by cstomo_sensor."""


class ConfigError(CstomoError, ValueError):
    """A geometry, scene, parameter or file value is missing or out of range (names the field)."""


class FrameError(CstomoError, ValueError):
    """A frame of voltages is malformed (wrong length, NaN/Inf, unparsable)."""


class ModelMismatchError(CstomoError, ValueError):
    """A cached or saved model was built for other inputs than the ones asked for."""


class MeshError(CstomoError, RuntimeError):
    """Meshing failed or produced a mesh that does not meet the quality bounds."""


class BoardError(CstomoError, IOError):
    """The board or its serial link failed."""


class BoardTimeoutError(BoardError, TimeoutError):
    """The board did not answer in time."""
