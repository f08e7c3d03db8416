"""The robot side: the edge bundle, simulated robots, the power device, the camera view, the
evaluation benches and the watchdog."""
