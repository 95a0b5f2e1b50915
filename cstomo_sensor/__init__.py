"""cstomo_sensor: force-direction sensing with electrical impedance tomography of conductive rubber.

Layers, one folder each: :mod:`.model` (the sensor and its physics), :mod:`.inverse` (Landweber and
the reconstruction model), :mod:`.force` (from a frame's change to a force, in rooms: estimators, checks, slow_states,
reference), :mod:`.frame_path` (a sensor's frames from a source through the stream to its outputs), :mod:`.board`
(wire protocol, serial driver, simulated board), :mod:`.ros` (the node) and :mod:`.tools` (the
command line); beside them the shared helpers :mod:`.errors`, :mod:`.cache`, :mod:`.frames_io` and
:mod:`.angles`. The core never imports :mod:`.ros` or :mod:`.tools` and imports with numpy, scipy,
PyYAML and pyserial alone; rclpy loads only in :mod:`.ros` and :mod:`.tools`.
"""
__version__ = "0.1.0"
