"""The clone's half of the offloading example: /scan (sensor_msgs/LaserScan) from the robot in,
/map (nav_msgs/OccupancyGrid, transient local: a late subscriber gets the last one) out, one map
per scan, with /map_stats (the workspace's own ccrp_offload_msgs/MapStats: a summary another
clone can import) and the service /last_map (ccrp_offload_msgs/LastMap). Run: python3 -m
ccrp_offload.scan_to_map (ccrp's unit ccrp-run-mapper on the clone)."""
import array
import os

import rclpy
from nav_msgs.msg import OccupancyGrid
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from ccrp_offload_msgs.msg import MapStats
from ccrp_offload_msgs.srv import LastMap

from ccrp_offload import VERSION, grid

MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class ScanToMap(Node):
    def __init__(self):
        super().__init__("scan_to_map")
        self.maps = self.create_publisher(OccupancyGrid, "/map", MAP_QOS)
        self.stats = self.create_publisher(MapStats, "/map_stats", MAP_QOS)
        self.last = None
        self.create_service(LastMap, "/last_map", self.on_last_map)
        self.create_subscription(LaserScan, "/scan", self.on_scan, 10)
        self.get_logger().info(f"ccrp_offload {VERSION} started")

    def on_scan(self, scan):
        angles = grid.beam_angles(scan.angle_min, scan.angle_increment, len(scan.ranges))
        cells = grid.scan_to_grid(scan.ranges, angles, scan.range_min, scan.range_max)
        m = OccupancyGrid()
        m.header = scan.header  # the map is in the scan's frame, of the scan's time
        m.info.map_load_time = scan.header.stamp
        m.info.resolution = grid.RESOLUTION
        m.info.width, m.info.height = grid.WIDTH, grid.HEIGHT
        m.info.origin.position.x, m.info.origin.position.y = grid.origin()
        m.info.origin.orientation.w = 1.0
        m.data = array.array("b", cells)
        self.maps.publish(m)
        stats = MapStats(header=scan.header, robot=os.environ.get("CCRP_ROBOT", ""), version=VERSION,
                         width=grid.WIDTH, height=grid.HEIGHT, occupied=cells.count(grid.OCCUPIED), free=cells.count(grid.FREE))
        self.stats.publish(stats)
        self.last = stats

    def on_last_map(self, request, response):
        response.found = self.last is not None
        if self.last is not None:
            response.stats = self.last
        return response


def main():
    rclpy.init()
    node = ScanToMap()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # SIGINT, or systemd's SIGTERM
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
