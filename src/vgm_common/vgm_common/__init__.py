"""Shared pieces of the vision-guided manipulation graph: message/numpy conversion, exact-time
sync, QoS profiles, scenario loading, camera and PA-10 models, diagnostics, the process
launcher."""
