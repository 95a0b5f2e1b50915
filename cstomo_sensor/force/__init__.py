"""From a frame's change to a force and its error bar, in four rooms, each importing only the ones before it:
estimators, checks, slow_states, reference (the frame path that drives them: cstomo_sensor.frame_path)."""
