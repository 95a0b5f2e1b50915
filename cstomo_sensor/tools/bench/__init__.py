"""``cstomo bench`` and ``cstomo bench-node``: held-out scenes (:mod:`.scenes`), models per setting
(:mod:`.models`), per-frame timing (:mod:`.timing`), the speed/accuracy table (:mod:`.table`) and its
report (:mod:`.report`), held-out forces (:mod:`.heldout`), GREIT figures (:mod:`.greit`), the pyEIT
comparison (:mod:`.pyeit`), the node itself (:mod:`.node`) and the floor of a Python node (:mod:`.lean`);
the command in :mod:`.main`."""
