"""Difference imaging: the Landweber iteration and its closed form (:mod:`.landweber`), and the
precomputed reconstruction model R on a voxel basis (:mod:`.reconstruction`). Pure numerics."""
