"""ccrp's offloading example: a robot's laser scans become an occupancy grid on its clone."""

# Logged at start ("ccrp_offload 1.0 started"): change it to see a new build reach the clones.
VERSION = "1.0"
