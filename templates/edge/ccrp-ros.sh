# ccrp: ROS environment (ROS 1: ROS_MASTER_URI points at the robot's clone; ROS 2: the robot's
# domain, with its clone as the only DDS peer, and the distro's setup.sh).
set -a
. /etc/ccrp/ros.env
set +a
if [ -z "${ROS_MASTER_URI:-}" ] && [ -f "/opt/ros/${ROS_DISTRO:-}/setup.sh" ]; then
    . "/opt/ros/${ROS_DISTRO}/setup.sh"
fi
