// a flat spur gear with spokes: 40 teeth, 4 mm thick
module gear2d(teeth = 40, r = 35, depth = 2.5) {
  polygon([for (k = [0:teeth * 8 - 1])
    let (a = 360 * k / (teeth * 8), phase = k % 8,
         rr = (phase < 3) ? r : (phase == 3 || phase == 7) ? r - depth / 2 : r - depth)
    [rr * cos(a), rr * sin(a)]]);
}
difference() {
  linear_extrude(height = 4) gear2d();
  translate([0, 0, -1]) cylinder(h = 10, r = 6, $fn = 6);
  for (a = [0:60:300]) rotate(a) translate([19, 0, -1]) cylinder(h = 10, r = 6.5, $fn = 48);
}
