"""cstomo_sensor: force-direction sensing with electrical impedance tomography of conductive rubber.

The numerical core (geometry, pattern, mesh data, fem, reconstruction, material, estimate) imports
with numpy, scipy and PyYAML alone; pyvista/pytetwild, scikit-fem, pyserial and rclpy are imported
only by the modules that need them.
"""
__version__ = "0.1.0"
