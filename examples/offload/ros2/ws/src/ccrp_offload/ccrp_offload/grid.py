"""The occupancy grid of one laser scan, without ROS (the ROS 1 node's src/grid.h is the same).

The grid is WIDTH x HEIGHT cells of RESOLUTION metres, centred on the robot (the scan's origin).
For each beam, the cells it crosses are free (0) and the cell it hits is occupied (100); every
other cell is unknown (-1). Cells are row-major from the grid's origin (its -x, -y corner), the
order of nav_msgs/OccupancyGrid's data. A hit wins over a free cell of another beam.
"""
import math

WIDTH = 100
HEIGHT = 100
RESOLUTION = 0.05  # metres per cell: 100 cells of 0.05 m = 5 m x 5 m

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


def origin(width=WIDTH, height=HEIGHT, resolution=RESOLUTION):
    """The (x, y) of the grid's corner cell, in the scan's frame: the robot is at the centre."""
    return -width * resolution / 2.0, -height * resolution / 2.0


def beam_angles(angle_min, angle_increment, count):
    """Each beam's angle as LaserScan defines it."""
    return [angle_min + k * angle_increment for k in range(count)]


def cell_of(x, y, width=WIDTH, height=HEIGHT, resolution=RESOLUTION):
    """The (column, row) of the cell holding the point, possibly outside the grid."""
    ox, oy = origin(width, height, resolution)
    return int(math.floor((x - ox) / resolution)), int(math.floor((y - oy) / resolution))


def line(c0, r0, c1, r1):
    """The cells from (c0, r0) to (c1, r1), both included (Bresenham, all octants)."""
    dc, dr = abs(c1 - c0), -abs(r1 - r0)
    sc, sr = (1 if c0 < c1 else -1), (1 if r0 < r1 else -1)
    err = dc + dr
    cells = []
    while True:
        cells.append((c0, r0))
        if c0 == c1 and r0 == r1:
            return cells
        e2 = 2 * err
        if e2 >= dr:
            err += dr
            c0 += sc
        if e2 <= dc:
            err += dc
            r0 += sr


def scan_to_grid(ranges, angles, range_min=0.0, range_max=math.inf,
                 width=WIDTH, height=HEIGHT, resolution=RESOLUTION):
    """The grid's cells (a list of width * height ints in -1, 0, 100) for one scan.

    A range that is NaN or under range_min is no reading; one at or over range_max (or infinite)
    saw nothing up to range_max: free cells, no hit."""
    cells = [UNKNOWN] * (width * height)
    hits = []
    c0, r0 = cell_of(0.0, 0.0, width, height, resolution)
    for r, a in zip(ranges, angles):
        if math.isnan(r) or r < range_min:
            continue
        hit = r < range_max
        reach = r if hit else range_max
        if math.isinf(reach):
            continue
        c1, r1 = cell_of(reach * math.cos(a), reach * math.sin(a), width, height, resolution)
        path = line(c0, r0, c1, r1)
        if hit:
            hits.append(path.pop())
        for c, row in path:
            if not (0 <= c < width and 0 <= row < height):
                break  # the beam has left the grid
            cells[row * width + c] = FREE
    for c, row in hits:
        if 0 <= c < width and 0 <= row < height:
            cells[row * width + c] = OCCUPIED
    return cells


def counts(cells):
    """{"occupied": N, "free": M, "unknown": K}: the summary wait_map.py prints."""
    return {"occupied": sum(1 for v in cells if v == OCCUPIED),
            "free": sum(1 for v in cells if v == FREE),
            "unknown": sum(1 for v in cells if v == UNKNOWN)}
