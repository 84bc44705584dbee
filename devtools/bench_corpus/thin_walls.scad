// thin walls: a comb of 0.5 to 1.1 mm fins on a base, and a 0.8 mm tube
union() {
  cube([60, 20, 1.6]);
  for (i = [0:6]) translate([4 + i * 8, 2, 0]) cube([0.5 + 0.1 * i, 16, 20]);
  translate([75, 10, 0]) difference() {
    cylinder(h = 25, r = 8, $fn = 96);
    translate([0, 0, 1.6]) cylinder(h = 30, r = 7.2, $fn = 96);
  }
}
