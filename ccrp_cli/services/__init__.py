"""The clone services (docs/architecture.md, "Clone services"): what runs on a clone beside OpenVPN and
ROS, each a plug-in (base.py CloneService) in the registry's order (registry.py): the relay
(sharing.py), autostop, robot power, the API manager, knowledge sync, the robot's own nodes
(workloads.py), the camera view."""
