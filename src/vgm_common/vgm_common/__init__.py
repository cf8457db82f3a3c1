"""Shared pieces of the vision-guided manipulation graph: message/numpy conversion, exact-time
sync, QoS profiles, camera and robot models, settings and parameters, diagnostics, the
process launcher."""
