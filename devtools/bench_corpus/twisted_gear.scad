// a twisted (herringbone-less helical) gear: 24 teeth, 30 degrees of twist over 10 mm
module gear2d(teeth = 24, r = 18, depth = 2.2) {
  polygon([for (k = [0:teeth * 8 - 1])
    let (a = 360 * k / (teeth * 8), phase = k % 8,
         rr = (phase < 3) ? r : (phase == 3 || phase == 7) ? r - depth / 2 : r - depth)
    [rr * cos(a), rr * sin(a)]]);
}
difference() {
  linear_extrude(height = 10, twist = 30, slices = 40) gear2d();
  translate([0, 0, -1]) cylinder(h = 20, r = 5, $fn = 64);
}
