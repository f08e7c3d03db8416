// The occupancy grid of one laser scan, without ROS: the same as the ROS 2 package's
// ccrp_offload/grid.py, cell for cell (tests/unit/test_offload_example.py compares them).
//
// WIDTH x HEIGHT cells of RESOLUTION metres, centred on the robot (the scan's origin). For each
// beam, the cells it crosses are free (0) and the cell it hits is occupied (100); every other
// cell is unknown (-1). Row-major from the grid's -x, -y corner, as nav_msgs/OccupancyGrid.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <utility>
#include <vector>

namespace ccrp_offload {

const int WIDTH = 100;
const int HEIGHT = 100;
const double RESOLUTION = 0.05;  // metres per cell: 100 cells of 0.05 m = 5 m x 5 m
const int8_t UNKNOWN = -1, FREE = 0, OCCUPIED = 100;

inline double origin_x() { return -WIDTH * RESOLUTION / 2.0; }
inline double origin_y() { return -HEIGHT * RESOLUTION / 2.0; }

typedef std::pair<int, int> Cell;  // (column, row), possibly outside the grid

inline Cell cell_of(double x, double y) {
  return Cell(static_cast<int>(std::floor((x - origin_x()) / RESOLUTION)),
              static_cast<int>(std::floor((y - origin_y()) / RESOLUTION)));
}

// The cells from a to b, both included (Bresenham, all octants).
inline std::vector<Cell> line(Cell a, Cell b) {
  int c0 = a.first, r0 = a.second;
  const int c1 = b.first, r1 = b.second;
  const int dc = std::abs(c1 - c0), dr = -std::abs(r1 - r0);
  const int sc = c0 < c1 ? 1 : -1, sr = r0 < r1 ? 1 : -1;
  int err = dc + dr;
  std::vector<Cell> cells;
  while (true) {
    cells.push_back(Cell(c0, r0));
    if (c0 == c1 && r0 == r1) return cells;
    const int e2 = 2 * err;
    if (e2 >= dr) { err += dr; c0 += sc; }
    if (e2 <= dc) { err += dc; r0 += sr; }
  }
}

inline bool inside(const Cell& c) {
  return c.first >= 0 && c.first < WIDTH && c.second >= 0 && c.second < HEIGHT;
}

// A range that is NaN or under range_min is no reading; one at or over range_max (or infinite)
// saw nothing up to range_max: free cells, no hit. A hit wins over another beam's free cell.
inline std::vector<int8_t> scan_to_grid(const std::vector<float>& ranges, double angle_min,
                                        double angle_increment, double range_min,
                                        double range_max) {
  std::vector<int8_t> cells(WIDTH * HEIGHT, UNKNOWN);
  std::vector<Cell> hits;
  const Cell robot = cell_of(0.0, 0.0);
  for (size_t k = 0; k < ranges.size(); ++k) {
    const double r = ranges[k];
    const double a = angle_min + k * angle_increment;
    if (std::isnan(r) || r < range_min) continue;
    const bool hit = r < range_max;
    const double reach = hit ? r : range_max;
    if (std::isinf(reach)) continue;
    std::vector<Cell> path = line(robot, cell_of(reach * std::cos(a), reach * std::sin(a)));
    if (hit) {
      hits.push_back(path.back());
      path.pop_back();
    }
    for (size_t i = 0; i < path.size(); ++i) {
      if (!inside(path[i])) break;  // the beam has left the grid
      cells[path[i].second * WIDTH + path[i].first] = FREE;
    }
  }
  for (size_t i = 0; i < hits.size(); ++i)
    if (inside(hits[i])) cells[hits[i].second * WIDTH + hits[i].first] = OCCUPIED;
  return cells;
}

}  // namespace ccrp_offload
