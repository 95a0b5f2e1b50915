"""The channel mask of one sensor: the measurements a frame's status flags exclude. No ROS, no serial.

A stage of the frame stream (frame_path/stream.py) and the one owner of the mask: a board flags saturated
values and electrodes whose contact failed; every measurement of a dead electrode and every saturated
value is excluded. The stream hands a changed mask to the pipeline (its reconstruction and estimator)
and to the drift tracker; they receive it, none keeps its own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import NoUsableChannelsError
from ..model.pattern import MeasurementPattern


@dataclass(frozen=True)
class Excluded:
    """Channels excluded from the reconstruction by the latest frame's status flags."""

    saturated: int = 0
    dead_electrodes: tuple[int, ...] = ()
    channels: int = 0


class ChannelMask:
    """The mask (``True``: excluded) of a sensor of ``geometry``, starting as ``bad`` (n_meas,; None:
    nothing excluded, e.g. a sink's own mask for :meth:`flagged`)."""

    def __init__(self, geometry, bad: np.ndarray | None = None) -> None:
        n_el = len(geometry.electrodes)
        pattern = MeasurementPattern(n_el, geometry.layers)
        self._electrode_rows = np.stack([pattern.electrode_rows(e) for e in range(n_el)])
        self._all_good = np.ones(n_el, bool)
        if bad is None:
            bad = np.zeros(self._electrode_rows.shape[1], bool)
        self.use(np.array(bad, bool), Excluded(channels=int(np.count_nonzero(bad))))

    def of(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None):
        """(mask, saturated count, dead electrodes) of a frame's flags; raises
        :class:`NoUsableChannelsError` when they exclude every measurement."""
        contact = self._all_good if contact_ok is None else np.asarray(contact_ok, bool)
        dead = ~contact
        mask = self._electrode_rows[dead].any(axis=0) if dead.any() else np.zeros_like(self.mask)
        n_sat = 0
        if saturated is not None:
            saturated = np.asarray(saturated, bool)
            n_sat = int(np.count_nonzero(saturated))
            mask |= saturated
        if mask.all():
            raise NoUsableChannelsError(
                f"every measurement excluded ({n_sat} saturated values, {int(dead.sum())} of {dead.size} "
                "electrode contacts failed): frame dropped; check the sensor's cable, contacts and drive current")
        return mask, n_sat, dead

    def flagged(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> np.ndarray | None:
        """The measurements a frame's flags exclude (saturated, every row of a dead electrode), or None
        when nothing is flagged (the common case)."""
        if (saturated is None or not np.count_nonzero(saturated)) and (
                contact_ok is None or np.count_nonzero(contact_ok) == len(contact_ok)):
            return None
        try:
            return self.of(saturated, contact_ok)[0]
        except NoUsableChannelsError:
            return np.ones(len(self.mask), bool)

    def change(self, saturated: np.ndarray | None, contact_ok: np.ndarray | None) -> tuple | None:
        """The (mask, :class:`Excluded`) a frame's flags ask for when it differs from the one in use,
        else None (nothing changes until :meth:`use`). Raises :class:`NoUsableChannelsError` when the
        flags exclude every measurement."""
        if not self.excluded.channels and (saturated is None or not np.count_nonzero(saturated)) and (
                contact_ok is None or np.count_nonzero(contact_ok) == len(contact_ok)):
            return None  # the common case, per frame: nothing flagged and nothing excluded
        mask, n_sat, dead = self.of(saturated, contact_ok)
        if np.array_equal(mask, self.mask):
            return None
        return mask, Excluded(saturated=n_sat, dead_electrodes=tuple(int(e) for e in np.flatnonzero(dead)),
                              channels=int(mask.sum()))

    def use(self, mask: np.ndarray, excluded: Excluded) -> None:
        """The mask of :meth:`change`, once the pipeline took it."""
        self.mask, self.excluded = mask, excluded
        self.frozen = mask if excluded.channels else None  # the excluded channels, None when none is
        self.kept = ~mask if excluded.channels else None  # ... and the others

    def status(self) -> tuple[list[str], dict]:
        """The diagnostics' problems and figures."""
        ex = self.excluded
        kv = dict(saturated_channels=ex.saturated, dead_electrodes=",".join(str(e + 1) for e in ex.dead_electrodes),
                  excluded_channels=ex.channels)
        msgs = [f"{ex.channels} channels excluded (saturated {ex.saturated}, dead electrodes "
                f"{[e + 1 for e in ex.dead_electrodes]})"] if ex.channels else []
        return msgs, kv
