// an L bracket with holes and a rib, for the 0.6 mm nozzle
difference() {
  union() {
    cube([60, 30, 5]);
    cube([60, 5, 30]);
    translate([28, 0, 0]) rotate([90, 0, 90]) linear_extrude(4) polygon([[5, 5], [28, 5], [5, 28]]);
  }
  for (x = [12, 48]) translate([x, 18, -1]) cylinder(h = 10, r = 2.7, $fn = 40);
  for (x = [12, 48]) translate([x, -1, 18]) rotate([-90, 0, 0]) cylinder(h = 10, r = 2.7, $fn = 40);
}
