"""The command line (``cstomo``) and what runs from it: the simulated board's command, demo, replay,
render and the benchmarks (:mod:`.bench`). May import every other layer; nothing imports it."""
