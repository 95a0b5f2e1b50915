"""The drive and measurement order (docs/physics.md#measurement-order), generated from the pair-list rule.

Electrodes are numbered from 1 in documents and from 0 in arrays; every array here is 0-based.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import ConfigError
from .geometry import N_ELECTRODES


def pair_list(n_electrodes: int = N_ELECTRODES, layers: int = 1) -> np.ndarray:
    """Adjacent pairs, ring by ring: one layer (1,2)..(16,1); two layers (1,2)..(8,1),(9,10)..(16,9).

    Returns
    -------
    pairs : (n_electrodes, 2) int ndarray, 0-based electrode indices.
    """
    if layers not in (1, 2) or n_electrodes % layers or n_electrodes // layers < 3:
        raise ConfigError(f"{n_electrodes=} with {layers=}: expected 1 or 2 rings of at least 3 electrodes")
    ring = n_electrodes // layers
    first = np.arange(n_electrodes)
    second = (first // ring) * ring + (first % ring + 1) % ring
    return np.stack([first, second], axis=1)


@dataclass(frozen=True)
class MeasurementPattern:
    """For each drive pair (a, b) in pair order (+I into a, out of b), every pair (m, n) in pair order
    sharing no electrode with (a, b) gives V = phi(m) - phi(n)."""

    n_electrodes: int = N_ELECTRODES
    layers: int = 1

    @cached_property
    def pairs(self) -> np.ndarray:
        """(n_pairs, 2) adjacent pairs, 0-based."""
        return pair_list(self.n_electrodes, self.layers)

    @cached_property
    def rows(self) -> np.ndarray:
        """(n_meas, 2) indices into :attr:`pairs`: (drive pair index, measure pair index) per value."""
        p = self.pairs
        out = [
            (d, m)
            for d in range(len(p))
            for m in range(len(p))
            if not set(p[d].tolist()) & set(p[m].tolist())
        ]
        return np.array(out, dtype=int)

    @property
    def n_meas(self) -> int:
        return len(self.rows)

    @property
    def drive(self) -> np.ndarray:
        """(n_meas, 2) driven electrodes (source, sink) of each value, 0-based."""
        return self.pairs[self.rows[:, 0]]

    @property
    def measure(self) -> np.ndarray:
        """(n_meas, 2) measured electrodes (m, n) of each value, V = phi(m) - phi(n), 0-based."""
        return self.pairs[self.rows[:, 1]]

    def electrode_rows(self, electrode: int) -> np.ndarray:
        """Boolean (n_meas,) mask of the values that drive or measure through ``electrode`` (0-based)."""
        return np.any(self.drive == electrode, axis=1) | np.any(self.measure == electrode, axis=1)

    def voltages(self, electrode_potentials: np.ndarray) -> np.ndarray:
        """Pick the measured differences from electrode potentials.

        Parameters
        ----------
        electrode_potentials : (n_pairs, n_electrodes) ndarray, potentials of every electrode under
            each drive pair in pair order.

        Returns
        -------
        (n_meas,) ndarray in the order of docs/physics.md#measurement-order.
        """
        d, m = self.rows[:, 0], self.measure
        return electrode_potentials[d, m[:, 0]] - electrode_potentials[d, m[:, 1]]


def pattern_for(geometry) -> MeasurementPattern:
    return MeasurementPattern(geometry.n_electrodes, geometry.layers)
