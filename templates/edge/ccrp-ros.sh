# ccrp: ROS environment (ROS_MASTER_URI points at the robot's clone).
set -a
. /etc/ccrp/ros.env
set +a
