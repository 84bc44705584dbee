// many small parts: 4 x 4 pegs and blocks, 6 mm tall (travel and retraction between each)
for (i = [0:3]) for (j = [0:3])
  translate([i * 14, j * 14, 0])
    if ((i + j) % 2 == 0) cylinder(h = 6, r = 3 + 0.4 * i, $fn = 40);
    else cube([6, 4 + j, 6], center = false);
