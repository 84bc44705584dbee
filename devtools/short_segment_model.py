"""An STL of curved parts with thin features: the model behind
tests/data/gcode/curves_0.6mm_*.gcode (many short segments, gap fill).

    python -m devtools.short_segment_model OUT.stl

then, with Debian's prusa-slicer 2.5 (the command in tests/data/gcode/README.md):
a finely faceted cylinder (perimeters of 0.2 mm segments), a ring with a
1.0 mm wall (gap fill between 0.6 mm perimeters), a wedge tapering to an edge
(gap fill and thin walls down to nothing) and a dome (curved top layers).
"""

from __future__ import annotations

import math
import sys
from typing import List, Tuple

Point = Tuple[float, float, float]
Facet = Tuple[Point, Point, Point]


def _prism(outline: List[Tuple[float, float]], z0: float, z1: float) -> List[Facet]:
    """A closed prism over a convex outline (counter-clockwise)."""
    facets: List[Facet] = []
    n = len(outline)
    cx = sum(p[0] for p in outline) / n
    cy = sum(p[1] for p in outline) / n
    for i in range(n):
        (ax, ay), (bx, by) = outline[i], outline[(i + 1) % n]
        facets.append(((cx, cy, z0), (bx, by, z0), (ax, ay, z0)))
        facets.append(((cx, cy, z1), (ax, ay, z1), (bx, by, z1)))
        facets.append(((ax, ay, z0), (bx, by, z0), (bx, by, z1)))
        facets.append(((ax, ay, z0), (bx, by, z1), (ax, ay, z1)))
    return facets


def _circle(cx: float, cy: float, r: float, n: int) -> List[Tuple[float, float]]:
    return [(cx + r * math.cos(2 * math.pi * i / n),
             cy + r * math.sin(2 * math.pi * i / n)) for i in range(n)]


def _ring(cx: float, cy: float, r_out: float, r_in: float, n: int, z1: float
          ) -> List[Facet]:
    facets: List[Facet] = []
    outer, inner = _circle(cx, cy, r_out, n), _circle(cx, cy, r_in, n)
    for i in range(n):
        j = (i + 1) % n
        (ax, ay), (bx, by) = outer[i], outer[j]
        (px, py), (qx, qy) = inner[i], inner[j]
        facets += [((ax, ay, 0), (bx, by, 0), (bx, by, z1)),
                   ((ax, ay, 0), (bx, by, z1), (ax, ay, z1)),
                   ((px, py, 0), (qx, qy, z1), (qx, qy, 0)),
                   ((px, py, 0), (px, py, z1), (qx, qy, z1)),
                   ((ax, ay, 0), (qx, qy, 0), (bx, by, 0)),
                   ((ax, ay, 0), (px, py, 0), (qx, qy, 0)),
                   ((ax, ay, z1), (bx, by, z1), (qx, qy, z1)),
                   ((ax, ay, z1), (qx, qy, z1), (px, py, z1))]
    return facets


def _dome(cx: float, cy: float, r: float, n: int, rings: int) -> List[Facet]:
    """A half sphere on z=0."""
    facets: List[Facet] = []

    def point(i: int, k: int) -> Point:
        phi = (math.pi / 2) * k / rings
        rr, z = r * math.cos(phi), r * math.sin(phi)
        return (cx + rr * math.cos(2 * math.pi * i / n),
                cy + rr * math.sin(2 * math.pi * i / n), z)
    for i in range(n):
        j = (i + 1) % n
        facets.append(((cx, cy, 0.0), point(j, 0), point(i, 0)))
        for k in range(rings):
            a, b, c, d = point(i, k), point(j, k), point(j, k + 1), point(i, k + 1)
            facets.append((a, b, c))
            if k + 1 < rings:
                facets.append((a, c, d))
    return facets


def model() -> List[Facet]:
    height = 12.0
    return (_prism(_circle(0, 0, 14, 440), 0, height)
            + _ring(38, 0, 12, 11, 360, height)
            + _prism([(-15, 22), (15, 22), (0, 62)], 0, height)
            + _dome(38, 40, 13, 240, 40))


def write_stl(path: str) -> None:
    with open(path, "w") as f:
        f.write("solid curves\n")
        for a, b, c in model():
            f.write(" facet normal 0 0 0\n  outer loop\n")
            for x, y, z in (a, b, c):
                f.write(f"   vertex {x:.5f} {y:.5f} {z:.5f}\n")
            f.write("  endloop\n endfacet\n")
        f.write("endsolid curves\n")


if __name__ == "__main__":
    write_stl(sys.argv[1])
