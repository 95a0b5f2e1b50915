"""The device's slow states since its tare: drift (and its tracker's parts), creep, the directions it learns, the
force's 1-sigma, and the coordinator that runs them per frame."""
