"""The ROS 2 edge: the lifecycle node (:mod:`.node`), its parameters and config (:mod:`.params`), the
messages it publishes (:mod:`.messages`) and the bridge that puts the library's log records on
``/rosout`` (:mod:`.log`). Imports the core, never :mod:`cstomo_sensor.tools`."""
