"""The model of what a structure costs on a scene (issue 17: no more model than the scene needs):
stats.py measures the scene on the device, bytes.py predicts each setting's buffers, cost.py its
work and time per ray and picks the cheapest setting under a device-memory budget, constants.py
stores the per-device constants that `lsbench fit` measures. docs/fit.md explains the model."""
