"""Code that runs ON a clone (standard library + the clone's ROS python only)."""
