"""Difference imaging: the Landweber iteration in closed form (:mod:`.landweber`), and the
precomputed reconstruction model R on a voxel basis (:mod:`.reconstruction`). Pure numerics."""
