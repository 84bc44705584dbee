// raised text on a thin plate: short strokes, many retractions
union() {
  cube([92, 22, 1.2]);
  translate([3, 4, 1.2]) linear_extrude(height = 3)
    text("flowloop 42", size = 12, font = "DejaVu Sans:style=Bold");
}
