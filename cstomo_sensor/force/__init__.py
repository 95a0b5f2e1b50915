"""From a frame to a force: the calibrated estimators (:mod:`.estimate`) and the per-frame path with
its settings, tare and channel masks (:mod:`.pipeline`), shared by the node, replay and the command
line. No ROS, no serial."""
