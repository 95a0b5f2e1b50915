"""The sensor and its physics, pure numerics: geometry (YAML presets), the material law, the drive and
measurement pattern, meshes, the complete electrode model (:mod:`.cem`), linear elasticity (the P2
problem :mod:`.elastic_fem`, the sensor's loads :mod:`.elasticity`) and the honest simulation of a
device. Imports numpy, scipy and PyYAML at load; pyvista, pytetwild and scikit-fem only inside the
functions that mesh or solve elasticity."""
