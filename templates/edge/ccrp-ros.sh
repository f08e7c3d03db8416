# ccrp: ROS environment of this robot (ROS_MASTER_URI points at its clone).
set -a
. /etc/ccrp/ros.env
set +a
