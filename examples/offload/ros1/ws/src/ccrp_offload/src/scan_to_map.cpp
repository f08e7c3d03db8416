// The clone's half of the offloading example (ROS 1): /scan (sensor_msgs/LaserScan) from the
// robot in, /map (nav_msgs/OccupancyGrid, latched) out, one map per scan. ccrp runs it as the
// unit ccrp-run-mapper: /opt/ccrp/workspace/lib/ccrp_offload/scan_to_map.
#include <cstdio>

#include <nav_msgs/OccupancyGrid.h>
#include <ros/ros.h>
#include <sensor_msgs/LaserScan.h>

#include "grid.h"

// Logged at start ("ccrp_offload 1.0 started"): change it to see a new build reach the clones.
#define CCRP_OFFLOAD_VERSION "1.0"

namespace {

ros::Publisher maps;

void on_scan(const sensor_msgs::LaserScan::ConstPtr& scan) {
  nav_msgs::OccupancyGrid m;
  m.header = scan->header;  // the map is in the scan's frame, of the scan's time
  m.info.map_load_time = scan->header.stamp;
  m.info.resolution = ccrp_offload::RESOLUTION;
  m.info.width = ccrp_offload::WIDTH;
  m.info.height = ccrp_offload::HEIGHT;
  m.info.origin.position.x = ccrp_offload::origin_x();
  m.info.origin.position.y = ccrp_offload::origin_y();
  m.info.origin.orientation.w = 1.0;
  m.data = ccrp_offload::scan_to_grid(scan->ranges, scan->angle_min, scan->angle_increment,
                                      scan->range_min, scan->range_max);
  maps.publish(m);
}

}  // namespace

int main(int argc, char** argv) {
  setvbuf(stdout, NULL, _IOLBF, 0);  // each log line at once, to a pipe too (systemd's journal)
  ros::init(argc, argv, "scan_to_map");
  ros::NodeHandle nh;
  maps = nh.advertise<nav_msgs::OccupancyGrid>("/map", 1, true);  // latched
  ros::Subscriber scans = nh.subscribe("/scan", 10, on_scan);
  ROS_INFO("ccrp_offload %s started", CCRP_OFFLOAD_VERSION);
  ros::spin();
  return 0;
}
