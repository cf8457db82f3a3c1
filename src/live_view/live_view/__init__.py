"""Serves the graph's topics to Foxglove over its WebSocket protocol, as foxglove_bridge
does: ROS 2 schemas, CDR forwarded unchanged, frame transforms for the 3D panel."""
