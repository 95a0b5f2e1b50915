"""From a frame to a force: the calibrated estimators (:mod:`.estimate`), the per-frame path
(:mod:`.pipeline`), the frame stream (:mod:`.stream`) and their settings (:mod:`.config`), shared by
the node, replay and the command line. No ROS, no serial."""
