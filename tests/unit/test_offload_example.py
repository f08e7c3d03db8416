"""examples/offload: the grid of a scan (the ROS 2 package's grid.py, and the ROS 1 package's
grid.h agreeing with it cell for cell), the packages' manifests, the robot side's scan and the two
inventories. No ROS needed: the nodes themselves run in tests of the feature's build."""

from __future__ import annotations

import importlib.util
import math
import shutil
import struct
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "offload"
ROS2_PKG = EXAMPLE / "ros2" / "ws" / "src" / "ccrp_offload"
ROS1_PKG = EXAMPLE / "ros1" / "ws" / "src" / "ccrp_offload"
DEPENDS = {"roscpp", "sensor_msgs", "nav_msgs"}


def load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


grid = load(ROS2_PKG / "ccrp_offload" / "grid.py", "offload_grid")
fake_scan = load(EXAMPLE / "robot" / "fake_scan.py", "offload_fake_scan")
wait_map = load(EXAMPLE / "robot" / "wait_map.py", "offload_wait_map")

W, H = grid.WIDTH, grid.HEIGHT


def f32(x: float) -> float:
    """x as a LaserScan carries it (float32)."""
    return struct.unpack("f", struct.pack("f", x))[0]


def at(cells, col, row):
    return cells[row * W + col]


def marked(cells, value):
    return {(i % W, i // W) for i, v in enumerate(cells) if v == value}


# -- the grid -------------------------------------------------------------------------------------


def test_the_grid_is_100_by_100_cells_of_5_cm_centred_on_the_robot():
    assert (W, H, grid.RESOLUTION) == (100, 100, 0.05)
    assert grid.origin() == (-2.5, -2.5)
    assert grid.cell_of(0.0, 0.0) == (50, 50)
    assert grid.cell_of(-2.5, -2.5) == (0, 0)
    assert grid.cell_of(2.49, 2.49) == (99, 99)


def test_no_scan_leaves_every_cell_unknown():
    cells = grid.scan_to_grid([], [])
    assert len(cells) == W * H and set(cells) == {-1}


def test_a_beam_frees_the_cells_it_crosses_and_occupies_the_one_it_hits():
    cells = grid.scan_to_grid([1.0], [0.0], 0.05, 10.0)  # straight ahead (+x), a wall at 1 m
    assert marked(cells, 100) == {(70, 50)}
    assert marked(cells, 0) == {(c, 50) for c in range(50, 70)}
    assert sum(1 for v in cells if v == -1) == W * H - 21


@pytest.mark.parametrize("angle, hit", [(math.pi / 2, (50, 70)), (math.pi, (30, 50)), (-math.pi / 2, (50, 30))])
def test_beams_in_every_direction(angle, hit):
    cells = grid.scan_to_grid([1.0], [angle], 0.05, 10.0)
    assert marked(cells, 100) == {hit}
    assert len(marked(cells, 0)) == 20


def test_the_row_is_y_and_the_column_x_as_in_occupancy_grid():
    cells = grid.scan_to_grid([0.5], [math.pi / 2], 0.05, 10.0)  # +y: row 60, column 50
    assert cells[60 * W + 50] == 100


def test_no_reading_and_nothing_seen():
    # NaN and under range_min: nothing at all; at range_max or infinite: free cells, no hit.
    assert set(grid.scan_to_grid([math.nan, 0.01], [0.0, 1.0], 0.05, 10.0)) == {-1}
    for far in (2.0, math.inf):
        cells = grid.scan_to_grid([far], [0.0], 0.05, 2.0)
        assert not marked(cells, 100)
        assert marked(cells, 0) == {(c, 50) for c in range(50, 91)}  # 2 m: the beam's last cell too
    assert set(grid.scan_to_grid([math.inf], [0.0])) == {-1}  # and no range_max: no reach


def test_a_beam_past_the_grid_frees_cells_up_to_its_edge_only():
    cells = grid.scan_to_grid([8.0], [0.3], 0.05, 10.0)  # the hit is 8 m away, off the grid
    assert not marked(cells, 100)
    free = marked(cells, 0)
    assert max(c for c, _ in free) == 99 and all(0 <= r < H for _, r in free)


def test_a_hit_wins_over_another_beams_free_cell():
    cells = grid.scan_to_grid([0.5, 1.0], [0.0, 0.0], 0.05, 10.0)
    assert at(cells, 60, 50) == 100 and at(cells, 70, 50) == 100
    assert at(cells, 65, 50) == 0


def test_the_line_is_8_connected_and_includes_both_ends():
    for end in [(7, 3), (-4, 9), (-6, -6), (0, -5), (3, 0)]:
        cells = grid.line(0, 0, *end)
        assert cells[0] == (0, 0) and cells[-1] == end
        assert len(cells) == max(abs(end[0]), abs(end[1])) + 1
        for (a, b), (c, d) in zip(cells, cells[1:]):
            assert max(abs(c - a), abs(d - b)) == 1


def room_grid():
    """What the clone makes of fake_scan.py's room, the values float32 as on the wire."""
    ranges = [f32(r) for r in fake_scan.room_ranges()]
    angles = grid.beam_angles(f32(fake_scan.ANGLE_MIN), f32(fake_scan.ANGLE_INCREMENT), len(ranges))
    return grid.scan_to_grid(ranges, angles, f32(fake_scan.RANGE_MIN), f32(fake_scan.RANGE_MAX))


def test_the_fake_room_is_2_by_3_m_seen_by_180_beams():
    ranges = fake_scan.room_ranges()
    assert len(ranges) == 180 == fake_scan.BEAMS
    assert min(ranges) == pytest.approx(1.0)
    assert max(ranges) <= math.hypot(1.0, 1.5) + 1e-9
    assert fake_scan.ANGLE_MIN + 180 * fake_scan.ANGLE_INCREMENT == pytest.approx(math.pi)


def test_the_fake_rooms_map_has_its_walls_occupied_and_its_inside_free():
    cells = room_grid()
    occupied, free = marked(cells, 100), marked(cells, 0)
    assert len(occupied) > 100 and len(free) > 1000
    cols = [c for c, _ in occupied]
    rows = [r for _, r in occupied]
    # Walls at x = +-1 m (columns 30 and 70) and y = +-1.5 m (rows 20 and 80), a cell either way.
    assert min(cols) in (29, 30) and max(cols) in (69, 70)
    assert min(rows) in (19, 20) and max(rows) in (79, 80)
    for c, r in occupied:
        assert min(abs(c - 30), abs(c - 70)) <= 1 or min(abs(r - 20), abs(r - 80)) <= 1
    assert all(29 <= c <= 70 and 19 <= r <= 80 for c, r in free)
    assert at(cells, 50, 50) == 0
    assert at(cells, 5, 5) == -1


def test_wait_map_counts_occupied_and_free_cells():
    m = SimpleNamespace(info=SimpleNamespace(width=2, height=2), data=[100, 0, -1, 0])
    assert wait_map.summary(m) == {"width": 2, "height": 2, "occupied": 1, "free": 2}


# -- the C++ grid (ROS 1) agrees with the Python one (ROS 2) ---------------------------------------

DRIVER = r"""
#include <cstdio>
#include "grid.h"
int main() {  // stdin: angle_min angle_increment range_min range_max n range...; scanf reads inf, nan
  double angle_min, angle_increment, range_min, range_max, r;
  size_t n;
  if (std::scanf("%lf %lf %lf %lf %zu", &angle_min, &angle_increment, &range_min, &range_max, &n) != 5) return 2;
  std::vector<float> ranges(n);
  for (size_t i = 0; i < n; ++i) {
    if (std::scanf("%lf", &r) != 1) return 2;
    ranges[i] = static_cast<float>(r);
  }
  std::vector<int8_t> cells = ccrp_offload::scan_to_grid(ranges, angle_min, angle_increment,
                                                         range_min, range_max);
  for (size_t i = 0; i < cells.size(); ++i) std::printf("%d\n", cells[i]);
  return 0;
}
"""


@pytest.fixture(scope="module")
def cpp_grid(tmp_path_factory):
    gxx = shutil.which("g++")
    if gxx is None:
        pytest.skip("no g++ on this host")
    d = tmp_path_factory.mktemp("grid_h")
    (d / "driver.cpp").write_text(DRIVER)
    exe = d / "driver"
    subprocess.run([gxx, "-O1", "-std=c++11", "-I", str(ROS1_PKG / "src"), "-o", str(exe), str(d / "driver.cpp")],
                   check=True, timeout=120)

    def run(ranges, angle_min, angle_increment, range_min, range_max):
        text = " ".join(repr(float(v)) for v in (angle_min, angle_increment, range_min, range_max))
        text += f" {len(ranges)} " + " ".join(repr(float(r)) for r in ranges)
        out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True, timeout=30)
        return [int(v) for v in out.stdout.split()]

    return run


def test_the_cpp_grid_is_the_python_grid_on_the_fake_room(cpp_grid):
    args = [f32(fake_scan.ANGLE_MIN), f32(fake_scan.ANGLE_INCREMENT), f32(fake_scan.RANGE_MIN), f32(fake_scan.RANGE_MAX)]
    ranges = [f32(r) for r in fake_scan.room_ranges()]
    assert cpp_grid(ranges, *args) == room_grid()


def test_the_cpp_grid_is_the_python_grid_on_a_small_odd_scan(cpp_grid):
    # Beams off the grid, at range_max, under range_min, infinite, NaN, crossing each other's cells.
    ranges = [f32(r) for r in (0.7, 3.9, 3.0, 0.01, math.inf, 1.234, math.nan, 0.3, 2.6)]
    angle_min, inc, rmin, rmax = f32(-2.9), f32(0.77), f32(0.05), f32(3.0)
    angles = grid.beam_angles(angle_min, inc, len(ranges))
    assert cpp_grid(ranges, angle_min, inc, rmin, rmax) == grid.scan_to_grid(ranges, angles, rmin, rmax)


# -- the packages ----------------------------------------------------------------------------------


def depends(root, tag):
    return {e.text.strip() for e in root.findall(tag)}


def test_the_ros2_package_is_ament_python_and_depends_on_rclpy_and_the_messages():
    root = ET.parse(ROS2_PKG / "package.xml").getroot()
    assert root.get("format") == "3" and root.findtext("name") == "ccrp_offload"
    assert depends(root, "exec_depend") == {"rclpy", "sensor_msgs", "nav_msgs", "ccrp_offload_msgs"}
    assert root.findtext("export/build_type") == "ament_python"
    assert (ROS2_PKG / "resource" / "ccrp_offload").is_file()
    setup = (ROS2_PKG / "setup.py").read_text()
    assert '"scan_to_map = ccrp_offload.scan_to_map:main"' in setup
    assert "share/ament_index/resource_index/packages" in setup
    assert 'if __name__ == "__main__":\n    main()' in (ROS2_PKG / "ccrp_offload" / "scan_to_map.py").read_text()


def test_the_ros2_interface_package_generates_the_map_summary_and_its_service():
    """ccrp_offload_msgs: ament_cmake with rosidl, every interface file named in its CMakeLists, the
    node publishing one and serving the other (map_stats.py reads both)."""
    pkg = ROS2_PKG.parent / "ccrp_offload_msgs"
    root = ET.parse(pkg / "package.xml").getroot()
    assert root.findtext("export/build_type") == "ament_cmake"
    assert depends(root, "buildtool_depend") == {"ament_cmake", "rosidl_default_generators"}
    assert root.findtext("member_of_group") == "rosidl_interface_packages"
    cmake = (pkg / "CMakeLists.txt").read_text()
    files = sorted(p.relative_to(pkg).as_posix() for p in pkg.rglob("*.*") if p.suffix in (".msg", ".srv", ".action"))
    assert files == ["msg/MapStats.msg", "srv/LastMap.srv"] and all(f'"{f}"' in cmake for f in files)
    node = (ROS2_PKG / "ccrp_offload" / "scan_to_map.py").read_text()
    assert 'create_publisher(MapStats, "/map_stats"' in node and 'create_service(LastMap, "/last_map"' in node
    assert '"map_stats = ccrp_offload.map_stats:main"' in (ROS2_PKG / "setup.py").read_text()


def test_the_ros1_package_is_catkin_with_a_cpp_node():
    root = ET.parse(ROS1_PKG / "package.xml").getroot()
    assert root.get("format") == "2" and root.findtext("name") == "ccrp_offload"
    assert depends(root, "buildtool_depend") == {"catkin"}
    assert depends(root, "build_depend") == DEPENDS and depends(root, "exec_depend") == DEPENDS
    cmake = (ROS1_PKG / "CMakeLists.txt").read_text()
    assert "add_executable(scan_to_map src/scan_to_map.cpp)" in cmake
    assert "RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION}" in cmake


def test_both_nodes_log_the_same_version_at_start():
    init = (ROS2_PKG / "ccrp_offload" / "__init__.py").read_text()
    assert 'VERSION = "1.0"' in init
    assert 'f"ccrp_offload {VERSION} started"' in (ROS2_PKG / "ccrp_offload" / "scan_to_map.py").read_text()
    cpp = (ROS1_PKG / "src" / "scan_to_map.cpp").read_text()
    assert '#define CCRP_OFFLOAD_VERSION "1.0"' in cpp
    assert 'ROS_INFO("ccrp_offload %s started", CCRP_OFFLOAD_VERSION)' in cpp


# -- the inventories ------------------------------------------------------------------------------


@pytest.mark.parametrize("ros, fleet, distro, command", [
    ("ros1", "offload1", "noetic", ["/opt/ccrp/workspace/lib/ccrp_offload/scan_to_map"]),
    ("ros2", "offload2", "jazzy", ["python3", "-m", "ccrp_offload.scan_to_map"]),
])
def test_the_inventories_run_the_workspace_on_two_nao_clones(ros, fleet, distro, command):
    from ccrp_cli.loader import inventory_model

    path = EXAMPLE / f"{ros}.yaml"
    data = yaml.safe_load(path.read_text())
    assert data["fleet"] == fleet and data["ros"]["distro"] == distro
    assert data["provider"]["kind"] == "docker"
    assert [(r["name"], r["type"]) for r in data["robots"]] == [("nao1", "nao"), ("nao2", "nao")]
    assert data["software"] == {"workspace": f"{ros}/ws", "run": [{"name": "mapper", "command": command}]}
    assert (path.parent / data["software"]["workspace"] / "src" / "ccrp_offload" / "package.xml").is_file()
    inv = inventory_model().model_validate(data)
    assert inv.ros.distro == distro
    # Its workspace resolves (every package.xml key has an entry in the recipe's rosdep table).
    from ccrp_cli.services.workloads import snapshot_software

    snap = snapshot_software(inv, path)
    assert snap.build_type == ("catkin" if ros == "ros1" else "ament") and snap.digest != "none"


def test_the_two_example_fleets_can_run_side_by_side():
    a, b = (yaml.safe_load((EXAMPLE / f"{ros}.yaml").read_text()) for ros in ("ros1", "ros2"))
    for key in (("provider", "public_cidr"), ("vpn", "pool"), ("common", "cidr")):
        assert a[key[0]][key[1]] != b[key[0]][key[1]]
