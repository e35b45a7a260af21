"""torch-free ctypes bindings for compiled estimator libraries."""
